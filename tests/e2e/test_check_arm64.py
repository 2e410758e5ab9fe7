"""`make check-arm64` without the emulation (systemd/check-arm64.sh; docs/install.md, "arm64").

The check itself runs arm64 Debian under qemu for minutes and stays out of `make test`; what
can be checked here is checked here: the script parses and is not part of `make test`, the
pose comparison (systemd/compare_replays.py) measures what it says on synthetic pairs, and the
replay the check runs on the board (`companion eval DIR`) needs none of the extras, so nothing
is compiled at run time (numba is the `sim` extra's).
"""

from __future__ import annotations

import importlib.util
import json
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from peers.refuse_extras import REFUSE_EXTRAS

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "systemd" / "check-arm64.sh"
CLIP = REPO / "tests" / "data" / "real" / "tum_fr1_rpy_clip"


def _compare_module() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "compare_replays", REPO / "systemd" / "compare_replays.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["compare_replays"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


cmp = _compare_module()


def test_the_script_parses_and_stays_out_of_make_test() -> None:
    r = subprocess.run(["bash", "-n", str(SCRIPT)], capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    makefile = (REPO / "Makefile").read_text()
    phony = re.search(r"^\.PHONY:(.*?)(?<!\\)\n", makefile, flags=re.M | re.S)
    assert phony is not None and "check-arm64" in phony.group(1).split()
    assert re.search(r"^check-arm64:.*\n\t.*bash systemd/check-arm64\.sh", makefile, re.M)
    for target in ("all", "test", "unit", "lint", "typecheck"):
        rule = re.search(rf"^{target}:(.*)$", makefile, flags=re.M)
        assert rule is not None and "check-arm64" not in rule.group(1), target
    # the root lives outside the tree and is reused; a run ends with the comparison's verdict
    text = SCRIPT.read_text()
    assert "ARM64_ROOT=${ARM64_ROOT:-/var/tmp/companion-arm64}" in text
    assert "--only-binary=:all:" in text and "compare_replays.py" in text
    # never the host's whole /dev in the root: proot runs a guest's umount and mknod on what
    # it binds, and debootstrap's second stage took the host's /dev/pts away that way
    binds = re.findall(r"-b (\S+)", text)
    assert "/dev/null" in binds and "/dev" not in binds and "/dev/pts" not in binds


def _quat_about(axis: list[float], angle_rad: float) -> np.ndarray:
    a = np.array(axis) / np.linalg.norm(axis)
    return np.array([math.cos(angle_rad / 2), *(math.sin(angle_rad / 2) * a)])


def _quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    w1, v1, w2, v2 = p[0], p[1:], q[0], q[1:]
    return np.array([w1 * w2 - v1 @ v2, *(w1 * v2 + w2 * v1 + np.cross(v1, v2))])


def test_rotation_angle_is_exact_near_zero_and_sign_blind() -> None:
    rng = np.random.default_rng(3)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    angles = np.concatenate([np.full(25, 1e-9), rng.uniform(0.1, 3.0, 25)])
    axes = rng.normal(size=(50, 3))
    q_b = np.array(
        [_quat_mul(qi, _quat_about(ax, th)) for qi, ax, th in zip(q, axes, angles, strict=True)]
    )
    got = cmp.rotation_angle_rad(q, q_b)
    np.testing.assert_allclose(got, angles, rtol=1e-6)  # 1e-9 rad survives: no acos near 1
    np.testing.assert_allclose(cmp.rotation_angle_rad(q, -q), 0.0, atol=1e-15)


def _write_replay(folder: Path, position_m: np.ndarray, quat_wxyz: np.ndarray) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    time_us = 100_000 + 33_333 * np.arange(len(position_m))
    rows = ["time_us,x_m,y_m,z_m,qw,qx,qy,qz,vx_m_s,vy_m_s,vz_m_s,reset_counter,quality_pct"]
    tum = []
    for t, p, q in zip(time_us.tolist(), position_m.tolist(), quat_wxyz.tolist(), strict=True):
        x, y, z = (repr(v) for v in p)
        qw, qx, qy, qz = (repr(v) for v in q)
        rows.append(f"{t},{x},{y},{z},{qw},{qx},{qy},{qz},0,0,0,0,90")
        tum.append(f"{t * 1e-6!r} {x} {y} {z} {qx} {qy} {qz} {qw}")
    (folder / "poses.csv").write_text("\n".join(rows) + "\n")
    (folder / "vo.tum").write_text("\n".join(tum) + "\n")


def _scene(n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    position_m = np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0)
    quat = rng.normal(size=(n, 4))
    return position_m, quat / np.linalg.norm(quat, axis=1, keepdims=True)


def test_compare_finds_the_row_and_size_of_a_difference(tmp_path: Path) -> None:
    position_m, quat = _scene()
    _write_replay(tmp_path / "x86", position_m, quat)
    # identical files: 0 m, 0 rad, exit 0
    _write_replay(tmp_path / "same", position_m, quat)
    assert cmp.main([str(tmp_path / "x86"), str(tmp_path / "same")]) == 0
    same = cmp.compare_dirs(tmp_path / "x86", tmp_path / "same", 1e-6)
    assert [(d.max_position_m, d.max_rotation_rad) for d in same] == [(0.0, 0.0)] * 2
    # 3e-7 m everywhere: within 1e-6 m; 4e-6 m on row 17 (a 3-4-5 step) and a 1e-4 rad turn
    nudged = position_m + 3e-7 / math.sqrt(3)
    nudged[17] += [0.0, 2.4e-6, 3.2e-6]
    turned = quat.copy()
    turned[17] = _quat_mul(quat[17], _quat_about([0, 0, 1], 1e-4))
    _write_replay(tmp_path / "arm64", nudged, turned)
    for d in cmp.compare_dirs(tmp_path / "x86", tmp_path / "arm64", 1e-6):
        assert d.first_row_over_tolerance == 17 and d.first_time_mismatch_row is None
        assert d.max_position_m == pytest.approx(4e-6 + 3e-7, rel=0.05)
        assert d.max_rotation_rad == pytest.approx(1e-4, rel=1e-6)
        assert not d.within(1e-6) and d.within(1e-5)
    assert cmp.main([str(tmp_path / "x86"), str(tmp_path / "arm64")]) == 1
    assert cmp.main([str(tmp_path / "x86"), str(tmp_path / "arm64"), "--tolerance-m", "1e-5"]) == 0
    # different poses, equally accurate (the published ATEs of eval.json within 10 %): exit 3;
    # one clearly worse: exit 1
    for folder, ate_m in (("x86", 0.0406), ("arm64", 0.0401)):
        doc = {"tracks": {"published": {"ate_se3_m": ate_m}}}
        (tmp_path / folder / "eval.json").write_text(json.dumps(doc))
    assert cmp.main([str(tmp_path / "x86"), str(tmp_path / "arm64")]) == 3
    assert cmp.main([str(tmp_path / "x86"), str(tmp_path / "arm64"), "--ate-rel", "0.001"]) == 1
    worse = {"tracks": {"published": {"ate_se3_m": 0.06}}}
    (tmp_path / "arm64" / "eval.json").write_text(json.dumps(worse))
    assert cmp.main([str(tmp_path / "x86"), str(tmp_path / "arm64")]) == 1


def test_compare_refuses_other_times_and_names_a_bad_file(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    position_m, quat = _scene()
    _write_replay(tmp_path / "x86", position_m, quat)
    _write_replay(tmp_path / "short", position_m[:30], quat[:30])
    for d in cmp.compare_dirs(tmp_path / "x86", tmp_path / "short", 1e-6):
        assert d.rows == (40, 30) and d.first_time_mismatch_row == 30 and not d.within(1.0)
    # NaN on both sides (nothing published yet) is equal; on one side it is a difference
    both, one = position_m.copy(), position_m.copy()
    both[:3] = np.nan
    one[5] = np.nan
    _write_replay(tmp_path / "nan_a", both, quat)
    _write_replay(tmp_path / "nan_b", both, quat)
    _write_replay(tmp_path / "nan_one", one, quat)
    assert all(d.within(0.0) for d in cmp.compare_dirs(tmp_path / "nan_a", tmp_path / "nan_b", 0))
    d = cmp.compare_dirs(tmp_path / "x86", tmp_path / "nan_one", 1e-6)[1]
    assert d.first_row_over_tolerance == 5 and d.max_position_m == math.inf
    # a broken row: exit 2, the file and row named
    bad = tmp_path / "bad"
    _write_replay(bad, position_m, quat)
    lines = (bad / "poses.csv").read_text().splitlines()
    lines[4] = lines[4].replace(",", ",x", 1)
    (bad / "poses.csv").write_text("\n".join(lines) + "\n")
    assert cmp.main([str(tmp_path / "x86"), str(bad)]) == 2
    assert f"{bad / 'poses.csv'}: row 5" in capsys.readouterr().err
    assert cmp.main([str(tmp_path / "x86"), str(tmp_path / "absent")]) == 2
    assert "vo.tum: no such file" in capsys.readouterr().err


# `companion eval DIR` on a real clip with every extra's module refused: it must replay and
# write its poses without trying to import any of them
_EVAL_PROBE = (
    r"""
import sys

BLOCKED = ("numba", "llvmlite", "skimage", "matplotlib", "evo", "tomli_w", "companion.sitl")
"""
    + REFUSE_EXTRAS
    + r"""
from companion.cli import main

code = main(["eval", sys.argv[1], "--out", sys.argv[2], "--no-progress"])
print("ATTEMPTS", ",".join(attempts) or "-", "EXIT", code)
"""
)


def test_the_replay_on_a_board_imports_no_extra(tmp_path: Path) -> None:
    frames = 30  # the clip's first second: the same code path as the whole clip, in seconds
    clip = tmp_path / "clip"
    (clip / "images").mkdir(parents=True)
    for name in ("calibration.toml", "groundtruth.txt", "ranges.csv"):
        shutil.copy2(CLIP / name, clip / name)
    meta = (CLIP / "meta.toml").read_text()
    (clip / "meta.toml").write_text(
        re.sub(r"^frames = \d+$", f"frames = {frames}", meta, count=1, flags=re.M)
    )
    rows = (CLIP / "frames.csv").read_text().splitlines()[: frames + 1]
    (clip / "frames.csv").write_text("\n".join(rows) + "\n")
    for row in rows[1:]:
        image = row.split(",")[2]
        shutil.copy2(CLIP / image, clip / image)
    out = tmp_path / "eval"
    r = subprocess.run(
        [sys.executable, "-c", _EVAL_PROBE, str(clip), str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
    )
    assert "ATTEMPTS - EXIT 0" in r.stdout, r.stdout[-2000:] + r.stderr[-3000:]
    poses = (out / "poses.csv").read_text().splitlines()
    assert poses[0].startswith("time_us,x_m,y_m,z_m,qw") and len(poses) > frames // 2
    # and the comparison reads what eval writes: a replay equals itself
    assert cmp.main([str(out), str(out)]) == 0


def test_the_stage_probe_is_reproducible_and_shows_a_changed_stage(tmp_path: Path) -> None:
    first = cmp.probe_frontend(CLIP, None)
    assert set(first) == set(cmp.PROBE_STAGES)
    assert first["decode"].shape == (2, 480, 640, 3) and len(first["corners"]) > 50
    np.savez(tmp_path / "x86.npz", **first)
    again = cmp.probe_frontend(CLIP, tmp_path / "x86.npz")  # fed the reference's inputs
    for stage, text in cmp.probe_diff(first, again):
        assert text.startswith("largest difference 0 (0 of"), (stage, text)
    # a KLT output moved by 0.25 px on one feature: that stage, that size, nothing before it
    moved = dict(again)
    moved["klt"] = again["klt"].copy()
    moved["klt"][7, 1] += 0.25
    diffs = dict(cmp.probe_diff(first, moved))
    assert diffs["klt"].startswith("largest difference 0.25 (1 of")
    assert diffs["subpix"].startswith("largest difference 0 (0 of")
