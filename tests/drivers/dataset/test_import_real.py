"""Real sequences: ``companion eval`` on the committed TUM RGB-D clip (tests/data/real/), the
manifest (config/real_sequences.toml) and its rebuild from the git snapshots in /work/.mirror
(absent in CI: those tests skip and say why)."""

from __future__ import annotations

import dataclasses
import json
import shutil
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.cli import main
from companion.drivers.dataset import open_dataset, read_tum
from companion.drivers.dataset.import_depth import beam_in_camera
from companion.drivers.dataset.import_manifest import extract, read_manifest, rebuild
from companion.drivers.dataset.import_write import DEFAULT_BEAMS

REPO = Path(__file__).resolve().parents[3]
CLIP = REPO / "tests/data/real/tum_fr1_rpy_clip"
MANIFEST = REPO / "config/real_sequences.toml"
SNAPSHOTS = Path("/work/.mirror")
MISSING_SNAPSHOTS = sorted(
    {e.repository for e in read_manifest(MANIFEST)}
    - {p.name.replace("+", "/", 1) for p in SNAPSHOTS.glob("*+*") if p.is_dir()}
)
needs_snapshots = pytest.mark.skipif(
    not shutil.which("git") or bool(MISSING_SNAPSHOTS),
    reason="the git snapshots of the real sequences are only on the lab machine: "
    f"{', '.join(MISSING_SNAPSHOTS) or 'git'} not in {SNAPSHOTS}",
)


def test_eval_on_the_committed_clip_tracks_through_its_rotation(tmp_path: Path) -> None:
    """240 frames of TUM fr1/rpy (8 s, hand-held, mostly rotation) through the real CLI.
    Measured 2026-11-28 at 307028c: every frame after the first pose tracked, 0 resets (the
    VO follows the rotation its 2D tracks agree on when PnP fails), raw VO Sim(3) ATE 5.5 %
    of the path; M-MSCwK over 87 frames after the 5 s settling: SE(3) ATE 0.049 m. Its
    Sim(3) scale (7.7) is not asserted: the camera turns about a point that moves a few
    centimetres, so the metric scale of the clip's translation is not observable (before the
    rotation hold: 74 % tracked, 13 resets). On an AMD EPYC the same commit (04e5b3e) gives
    a raw VO ATE of 11.0 %: OpenCV's SIMD path differs by CPU and a VO amplifies the last
    bits (docs/RESULTS.md). With the VO of c48bf95 on the EPYC (2026-11-30): 97.5 % tracked,
    1 reset, raw VO 6.6 %; on the Intel Xeon VM the same VO (dd50fd7 and 6e154ae, every pose
    the same; 2026-11-30): 95.4 % tracked, 3 resets, raw VO 8.6 % (its longest segment),
    M-MSCwK 0.031 m. 0.73 m of path makes that centimetres; the bound is set to catch a VO
    that loses the rotation (74 % tracked, 13 resets before the rotation hold), not one draw
    against another."""
    out = tmp_path / "eval"
    argv = ["eval", str(CLIP), "--methods", "all", "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    report = json.loads((out / "scale_metrics.json").read_text())
    assert report["ground_truth"] is True and report["distance_sensors"] == [0, 1, 2, 3]
    vo = report["vo"]
    assert vo["frames"] == 240 and vo["tracking_ratio"] >= 0.90 and vo["resets"] <= 4, vo
    assert np.isfinite(vo["ate_sim3_pct"]) and vo["ate_sim3_pct"] < 15.0
    methods = {m["method"]: m for m in report["methods"]}
    mmscwk = methods["M-MSCwK"]
    assert mmscwk["frames"] >= 60
    assert np.isfinite(mmscwk["ate_se3_m"]) and mmscwk["ate_se3_m"] < 0.08


def test_the_clip_ranges_are_the_depth_plus_the_sensor_noise() -> None:
    ds = open_dataset(CLIP)
    meta = tomllib.loads((CLIP / "meta.toml").read_text())
    assert meta["rangefinders_source"] == "synthesised from depth images"
    assert np.allclose(ds.T_body_cam, np.eye(4))
    assert len(ds.ranges) >= 0.85 * 4 * len(ds)  # few beams dropped at holes and edges
    measured = np.array([r.distance_m for r in ds.ranges])
    true = np.asarray(ds.true_range_m)
    assert np.all(np.isfinite(true)) and true.min() > 0.4 and true.max() < 6.0  # a Kinect
    err = measured - true
    assert np.max(np.abs(err)) < 0.05 and 0.007 < np.std(err) < 0.013  # sigma 1 cm
    assert all(r.signal_quality >= 2 for r in ds.ranges)
    # readings stamped at their depth image, within 20 ms of a frame
    frame_s = ds.frame_times_us * 1e-6
    for r in ds.ranges[::50]:
        assert np.min(np.abs(frame_s - r.time_us * 1e-6)) <= 0.020


def test_the_manifest_declares_what_may_be_committed() -> None:
    entries = {e.name: e for e in read_manifest(MANIFEST)}
    assert {"tum_fr1_rpy", "tum_fr1_rpy_clip", "tum_fr3_cabinet_kf", "rislab_downward"} <= set(
        entries
    )
    rislab = entries["rislab_downward"]
    assert rislab.commit is False and rislab.importer == "rislab"
    assert "local evaluation only" in rislab.licence and len(rislab.tree_sha256) == 64
    clip = entries["tum_fr1_rpy_clip"]
    assert clip.commit is True and "CC BY 4.0" in clip.licence
    meta = tomllib.loads((CLIP / "meta.toml").read_text())
    assert (meta["sequence"], meta["source_revision"]) == (clip.name, clip.revision)
    committed = {p.name for p in (REPO / "tests/data/real").iterdir() if p.is_dir()}
    assert all(entries[name].commit for name in committed)
    assert len(entries["tum_fr1_rpy"].sha256) == 1448


@needs_snapshots
def test_rebuild_from_the_snapshot_matches_the_depth(tmp_path: Path) -> None:
    """The cabinet keyframes rebuilt from their git snapshot: checksums pass, and every
    synthesised reading's point lies on the depth image of its frame (within 3 cm)."""
    assert main(["dataset", "rebuild", "tum_fr3_cabinet_kf", "--snapshots", str(SNAPSHOTS),
                 "--out", str(tmp_path), "--manifest", str(MANIFEST)]) == 0  # fmt: skip
    ds = open_dataset(tmp_path / "tum_fr3_cabinet_kf")
    assert len(ds) == 58 and len(ds.ranges) >= 200
    entry = {e.name: e for e in read_manifest(MANIFEST)}["tum_fr3_cabinet_kf"]
    src = extract(entry, SNAPSHOTS, tmp_path / "raw")
    beams = {rf.sensor_id: beam_in_camera(rf) for rf in DEFAULT_BEAMS}
    frame_of = {int(t): k for k, t in enumerate(ds.frame_times_us)}
    misses = 0
    for r, true_m in zip(ds.ranges, ds.true_range_m, strict=True):
        k = frame_of[r.time_us]  # keyframes: the depth image has the frame's stamp
        depth = cv2.imread(str(src / f"depth_imgs/{k:04d}_depth_raw.png"), cv2.IMREAD_UNCHANGED)
        o, d = beams[r.sensor_id]
        p = o + true_m * d
        uv, _ = ds.camera.project(p[None, :])
        u, v = np.rint(uv[0]).astype(int)
        misses += abs(depth[v, u] / 5000.0 - p[2]) > 0.03
    assert misses <= 0.05 * len(ds.ranges)


@needs_snapshots
def test_rebuild_refuses_a_changed_file_and_an_importer_not_built_here(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = MANIFEST.read_text()
    entry = {e.name: e for e in read_manifest(MANIFEST)}["tum_fr3_cabinet_kf"]
    good = entry.sha256["truth_cam_poses.txt"]
    doctored = tmp_path / "manifest.toml"
    doctored.write_text(text.replace(good, "0" * 64).replace('"rislab"', '"no-such-format"'))
    argv = ["dataset", "rebuild", "--snapshots", str(SNAPSHOTS), "--manifest", str(doctored)]
    assert main([*argv, "tum_fr3_cabinet_kf", "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "truth_cam_poses.txt: sha256" in err and "not the manifest's" in err
    assert main([*argv, "rislab_downward", "--out", str(tmp_path / "b")]) == 2
    assert "importer 'no-such-format' is not built here" in capsys.readouterr().err
    assert main([*argv, "no_such", "--out", str(tmp_path / "c")]) == 2


@needs_snapshots
def test_the_downward_flight_rebuilds_from_its_snapshot(tmp_path: Path) -> None:
    """60 frames of the RIS lab flight in the air: checksums pass, the frames keep their
    jittery stamps, the truth is metric (a few cm of motion per 60 Hz frame at most) and the
    synthesised sensors read the floor below the body."""
    entry = {e.name: e for e in read_manifest(MANIFEST)}["rislab_downward"]
    short = dataclasses.replace(entry, args={**entry.args, "frames": "1200:1260"})
    summary = rebuild(short, SNAPSHOTS, tmp_path / "ris")
    ds = open_dataset(tmp_path / "ris")
    assert summary.frames == len(ds) >= 55
    stamps_ms = np.diff([f.time_us for f in ds.frames()]) * 1e-3
    assert stamps_ms.min() < 8.0 and stamps_ms.max() > 25.0  # the source's jitter, kept
    _, poses = read_tum(tmp_path / "ris" / "groundtruth.txt")
    steps_m = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert 0.0 < steps_m.max() < 0.05
    assert len(ds.ranges) > 100


@needs_snapshots
def test_the_downward_flights_truth_moves_like_its_images(tmp_path: Path) -> None:
    """Images 1150-1450 of the RIS lab flight rebuilt: the truth's poses, the camera's mount
    and the lens of the manifest move the floor's KLT tracks as the images do (78 % of the
    flow over images 1150-2380 on 2026-12-01; the first conversion predicted worse than no
    motion: docs/decisions.md, "rislab's truth, reconciled with its images")."""
    from companion.drivers.dataset.truth_check import check_truth

    entry = {e.name: e for e in read_manifest(MANIFEST)}["rislab_downward"]
    short = dataclasses.replace(entry, args={**entry.args, "frames": "1150:1450"})
    rebuild(short, SNAPSHOTS, tmp_path / "ris")
    check = check_truth(open_dataset(tmp_path / "ris"), -0.013, offsets_s=(-0.05, 0.0, 0.05))
    assert check.pairs >= 40
    median_at = {round(o, 2): median for o, median, _ in check.truth_px}
    assert median_at[0.0] < 0.35 * check.no_motion_px
    assert median_at[0.0] < min(median_at[-0.05], median_at[0.05])


@needs_snapshots
def test_the_committed_clip_is_its_manifest_entrys_rebuild(tmp_path: Path) -> None:
    """The first 30 frames rebuilt from the snapshot: the same JPEG bytes, frame rows, ranges
    (the noise drawn in frame order from the same seed) and ground truth as the committed
    clip."""
    entry = {e.name: e for e in read_manifest(MANIFEST)}["tum_fr1_rpy_clip"]
    short = dataclasses.replace(entry, args={**entry.args, "frames": "0:30"})
    rebuild(short, SNAPSHOTS, tmp_path / "clip")
    got, ours = open_dataset(tmp_path / "clip"), open_dataset(CLIP)
    assert len(got) == 30
    for k in (0, 17, 29):
        assert got.frame_paths[k].read_bytes() == ours.frame_paths[k].read_bytes()
    assert np.array_equal(got.frame_times_us, ours.frame_times_us[:30])
    n = len(got.ranges)
    assert n >= 100 and got.ranges == ours.ranges[:n]
    assert np.allclose(got.gt_T_world_body, ours.gt_T_world_body[:30], atol=1e-9)
