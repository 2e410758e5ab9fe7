"""Small valid datasets (a recording of ours, a EuRoC folder) held as bytes, and the hostile or
damaged variants of them that tests/e2e/test_hostile_inputs.py and
tests/drivers/dataset/test_fuzz_dataset.py feed to the reader and to `companion eval`: files outside
the folder, FIFOs, decompression bombs, deep TOML, bad numbers, zero quaternions, torn and
reordered rows, random byte flips."""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from companion.config import load_config
from companion.drivers.dataset import DatasetWriter
from companion.types import AttitudeSample, CameraFrame, ImuSample, PoseEstimate, RangeSample

WIDTH, HEIGHT = 96, 72  # small frames: a case costs milliseconds
Files = dict[str, bytes]


def textured(k: int) -> np.ndarray:
    """Frame ``k`` of a slow pan over blurred noise (BGR, WIDTH x HEIGHT): trackable."""
    rng = np.random.default_rng(11)
    base = cv2.GaussianBlur(
        rng.integers(0, 256, (HEIGHT + 80, WIDTH + 80), dtype=np.uint8), (5, 5), 0
    )
    return cv2.cvtColor(
        np.ascontiguousarray(base[k : k + HEIGHT, k : k + WIDTH]), cv2.COLOR_GRAY2BGR
    )


def _pose(t: int, k: int) -> PoseEstimate:
    """A published pose as the service sends it (unknown velocity: NaN)."""
    return PoseEstimate(
        time_us=t,
        position_ned_m=np.array([0.01 * k, 0.0, -2.0]),
        quat_wxyz_ned_frd=np.array([1.0, 0.0, 0.0, 0.0]),
        velocity_ned_m_s=np.full(3, np.nan) if k == 0 else np.array([0.3, 0.0, 0.0]),
        covariance_6x6=np.eye(6) * 0.01,
        reset_counter=0,
        quality_pct=80,
    )


def write_recording(folder: Path, frames: int = 8) -> None:
    """A valid recording of ours: ``frames`` PNG frames with a range, an attitude, an IMU
    sample each and a published pose per frame."""
    cfg = load_config(overrides={"camera": {"width": WIDTH, "height": HEIGHT}})
    writer = DatasetWriter(folder, cfg)
    for k in range(frames):
        t = 1_000_000 + k * 33_333
        img = textured(k)
        ranges = [RangeSample(t - 5_000, 0, 3.0 + 0.01 * k, 0.1, 40.0, 100)]
        atts = [AttitudeSample(t - 1_000, np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3))]
        imus = [ImuSample(t - 2_000, np.array([0.0, 0.0, -9.81]), np.zeros(3), None)]
        writer.write_frame(CameraFrame(t, k, img), writer.encode(img), ranges, atts, imus)
        writer.write_pose(_pose(t, k))
    writer.close()


def write_euroc(folder: Path, frames: int = 8) -> None:
    """A valid EuRoC MAV folder of the same frames (grey PNG), with ground truth."""
    cam = folder / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    (cam / "sensor.yaml").write_text(
        "sensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0,\n"
        "    0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n"
        f"resolution: [{WIDTH}, {HEIGHT}]\ncamera_model: pinhole\n"
        "intrinsics: [80.0, 80.0, 47.5, 35.5] # fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\ndistortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n"
    )
    rows = ["#timestamp [ns],filename"]
    truth = ["#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z"]
    for k in range(frames):
        t_ns = 1_000_000_000 + k * 33_333_000
        cv2.imwrite(
            str(cam / "data" / f"{t_ns}.png"), cv2.cvtColor(textured(k), cv2.COLOR_BGR2GRAY)
        )
        rows.append(f"{t_ns},{t_ns}.png")
        truth.append(f"{t_ns},{0.01 * k},0.0,2.0,1.0,0.0,0.0,0.0")
    (cam / "data.csv").write_text("\n".join(rows) + "\n")
    gt = folder / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir()
    (gt / "data.csv").write_text("\n".join(truth) + "\n")


def snapshot(folder: Path) -> Files:
    """Every file under ``folder`` as {relative path: bytes}."""
    return {
        str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def materialise(files: Files, folder: Path) -> Path:
    """Write ``files`` into the new folder ``folder``; returns it."""
    for name, data in files.items():
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    return folder


# ------------------------------------------------------------------------------ images
def _chunk(kind: bytes, data: bytes) -> bytes:
    crc = zlib.crc32(kind + data) & 0xFFFFFFFF
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)


def png_bomb(side: int, level: int = 9) -> bytes:
    """A valid grey PNG of side x side black pixels: a few hundred kB that decode to side**2
    bytes (32768: 1 GB of pixels, about 1 MB on disk)."""
    z = zlib.compressobj(level)
    rows = bytes((side + 1) * min(side, 1024))
    parts = [z.compress(rows) for _ in range(max(1, side // 1024))]
    parts.append(z.flush())
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", ihdr)
        + _chunk(b"IDAT", b"".join(parts))
        + _chunk(b"IEND", b"")
    )


def png_of(width: int, height: int) -> bytes:
    """A PNG of noise of this size."""
    img = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    return bytes(cv2.imencode(".png", img)[1])


def set_png_size(data: bytes, width: int, height: int) -> bytes:
    """``data`` (a PNG) with its IHDR claiming another size (its CRC fixed)."""
    ihdr = data[16:29]
    new = struct.pack(">II", width, height) + ihdr[8:]
    return data[:8] + _chunk(b"IHDR", new) + data[33:]


# ------------------------------------------------------------------------------ edits
def replace_field(files: Files, name: str, row: int, column: str, value: str) -> None:
    """Set ``column`` of data row ``row`` (1 = the first after the header) in CSV ``name``."""
    lines = files[name].decode().split("\n")
    header = lines[0].split(",")
    fields = lines[row].split(",")
    fields[header.index(column)] = value
    lines[row] = ",".join(fields)
    files[name] = "\n".join(lines).encode()


def edit_text(files: Files, name: str, edit: Callable[[str], str]) -> None:
    """Replace text file ``name`` by ``edit`` of its text."""
    files[name] = edit(files[name].decode()).encode()


def make_fifo(path: Path) -> None:
    """A FIFO at ``path`` (replacing what is there)."""
    if path.exists() or path.is_symlink():
        path.unlink()
    os.mkfifo(path)


# ------------------------------------------------------------------------------ fuzzing
HOSTILE_TOKENS = (
    "nan",
    "inf",
    "-inf",
    "",
    " ",
    "x",
    "1e999",
    "-1",
    "0",
    "1.5",
    "-0",
    "9" * 30,
    "9" * 5000,
    "0x10",
    "1_000",
    "\u00e9",
    '"',
    "../x.png",
    "/etc/passwd",
    "/dev/zero",
    "99999999999999999999",
    "1,2",
    "true",
    "[1, 2]",
    "{a = 1}",
    "\t",
    "NaN",
    "1e-320",
    "x" * 3000,
)
TOML_VALUES = (
    "nan",
    "inf",
    "-1",
    "0",
    "9" * 400,
    "9" * 5000,
    '"x"',
    "true",
    "[]",
    "{}",
    "[[[[1]]]]",
    '"\\u0000"',
    "1e400",
    "[" * 40 + "]" * 40,
    "'../x'",
    "30000",
)


def _pick_file(rng: np.random.Generator, files: Files, suffixes: tuple[str, ...]) -> str | None:
    names = sorted(n for n in files if n.endswith(suffixes))
    return names[int(rng.integers(len(names)))] if names else None


def _flip_bytes(rng: np.random.Generator, files: Files) -> None:
    name = _pick_file(rng, files, ("",))
    if name and files[name]:
        data = bytearray(files[name])
        for _ in range(int(rng.integers(1, 9))):
            data[int(rng.integers(len(data)))] = int(rng.integers(256))
        files[name] = bytes(data)


def _truncate(rng: np.random.Generator, files: Files) -> None:
    name = _pick_file(rng, files, ("",))
    if name:
        files[name] = files[name][: int(rng.integers(len(files[name]) + 1))]


def _csv_field(rng: np.random.Generator, files: Files) -> None:
    name = _pick_file(rng, files, (".csv", ".txt", ".yaml"))
    if not name:
        return
    lines = files[name].decode("utf-8", "replace").split("\n")
    row = int(rng.integers(len(lines)))
    fields = lines[row].split(",")
    fields[int(rng.integers(len(fields)))] = HOSTILE_TOKENS[int(rng.integers(len(HOSTILE_TOKENS)))]
    lines[row] = ",".join(fields)
    files[name] = "\n".join(lines).encode()


def _csv_rows(rng: np.random.Generator, files: Files) -> None:
    name = _pick_file(rng, files, (".csv", ".txt"))
    if not name:
        return
    lines = files[name].decode("utf-8", "replace").split("\n")
    a, b = (int(v) for v in rng.integers(len(lines), size=2))
    op = int(rng.integers(5))
    if op == 0:
        lines.insert(a, lines[b])  # a duplicated row (or header)
    elif op == 1:
        lines[a], lines[b] = lines[b], lines[a]  # decreasing times
    elif op == 2:
        del lines[a]
    elif op == 3:
        lines = [line + ",extra" for line in lines]  # an extra column
    else:
        header = lines[0].split(",")
        del header[int(rng.integers(len(header)))]  # a missing column
        lines[0] = ",".join(header)
    files[name] = "\n".join(lines).encode()


def _toml(rng: np.random.Generator, files: Files) -> None:
    name = _pick_file(rng, files, (".toml",))
    if not name:
        return
    lines = files[name].decode("utf-8", "replace").split("\n")
    row = int(rng.integers(len(lines)))
    op = int(rng.integers(4))
    if op == 0 and "=" in lines[row]:
        key = lines[row].split("=")[0]
        lines[row] = f"{key}= {TOML_VALUES[int(rng.integers(len(TOML_VALUES)))]}"
    elif op == 1:
        del lines[row]
    elif op == 2:
        lines.insert(row, lines[int(rng.integers(len(lines)))])  # a duplicated key or table
    else:
        depth = int(rng.choice([20, 1000, 30_000]))
        lines.insert(row, "[" + ".".join(["t"] * depth) + "]" if rng.random() < 0.5 else "")
        lines.insert(row, "deep = " + "[" * depth + "]" * depth)
    files[name] = "\n".join(lines).encode()


def _image(rng: np.random.Generator, files: Files) -> None:
    name = _pick_file(rng, files, (".png", ".jpg"))
    if not name:
        return
    op = int(rng.integers(5))
    if op == 0:
        files[name] = png_of(WIDTH + int(rng.integers(1, 9)), HEIGHT)
    elif op == 1:
        side = int(rng.choice([30_000, 65_535, 2**31 - 1]))
        files[name] = set_png_size(files[name], side, side)  # a bomb's header
    elif op == 2:
        files[name] = bytes(cv2.imencode(".jpg", textured(0))[1])  # a JPEG named .png
    elif op == 3:
        files[name] = files[name][: int(rng.integers(8, 64))]
    else:
        files[name] = bytes(rng.integers(0, 256, int(rng.integers(1, 200)), dtype=np.uint8))


def _drop_or_empty(rng: np.random.Generator, files: Files) -> None:
    name = _pick_file(rng, files, ("",))
    if name and rng.random() < 0.5:
        del files[name]
    elif name:
        files[name] = b""


MUTATIONS = (
    _flip_bytes,
    _truncate,
    _csv_field,
    _csv_field,
    _csv_rows,
    _toml,
    _image,
    _drop_or_empty,
)


def _place(rng: np.random.Generator, folder: Path, outside: Path) -> None:
    """Now and then, a file-system hazard: a frame as a FIFO or a link out of the folder."""
    frames = sorted(p for p in folder.rglob("*.png"))
    if not frames or rng.random() > 0.05:
        return
    victim = frames[int(rng.integers(len(frames)))]
    if rng.random() < 0.5:
        make_fifo(victim)
    else:
        victim.unlink()
        victim.symlink_to(outside / "x.png")


def mutant(rng: np.random.Generator, base: Files) -> Files:
    """``base`` with 1 to 3 random mutations."""
    files = dict(base)
    for _ in range(int(rng.integers(1, 4))):
        MUTATIONS[int(rng.integers(len(MUTATIONS)))](rng, files)
    return files


class HangError(Exception):
    """A fuzz case that took longer than its bound."""


def _on_alarm(_signum: int, _frame: object) -> None:
    raise HangError()


def _read_all(folder: Path) -> None:
    """What `eval` reads: the dataset and every frame, in the pipeline's order."""
    from companion.drivers.dataset import open_dataset

    for _ in open_dataset(folder).events():
        pass


def _eval(folder: Path, out: Path, *flags: str) -> tuple[int, list[str]]:
    """`companion eval folder [flags]` in this process: its exit code and stderr lines."""
    import contextlib
    import io

    from companion.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(["eval", str(folder), "--out", str(out), "--no-progress", *flags])
    return code, err.getvalue().splitlines()


def fuzz(count: int, seed: int, eval_every: int, workdir: Path, case_limit_s: float) -> dict:
    """``count`` seeded mutants of a small recording of ours (3 in 4) and of a EuRoC folder,
    each read in full by the reader (every ``eval_every``-th through `companion eval`
    instead, every other one of those with ``--methods all``); returns the tally: cases,
    refusals (DatasetError), evals by exit code, and the failures: tracebacks, hangs (over
    ``case_limit_s``), messages of more than a line; the slowest case [s] and the process's
    peak RSS [MB]."""
    import shutil
    import signal
    import time
    import traceback

    from companion.errors import DatasetError
    from companion.offline import peak_rss_mb

    rng = np.random.default_rng(seed)
    write_recording(workdir / "ours")
    write_euroc(workdir / "euroc")
    bases = {"ours": snapshot(workdir / "ours"), "euroc": snapshot(workdir / "euroc")}
    outside = materialise(bases["ours"], workdir / "outside")
    (outside / "x.png").write_bytes(bases["ours"]["images/000000.png"])
    tally: dict = {
        "cases": 0,
        "read": 0,
        "refused": 0,
        "evals": {},
        "tracebacks": [],
        "hangs": [],
        "multiline": [],
        "slowest_s": 0.0,
    }
    signal.signal(signal.SIGALRM, _on_alarm)
    start = time.monotonic()
    for i in range(count):
        files = mutant(rng, bases["euroc" if rng.random() < 0.25 else "ours"])
        folder = materialise(files, workdir / "case")
        _place(rng, folder, outside)
        began = time.monotonic()
        signal.setitimer(signal.ITIMER_REAL, case_limit_s)
        try:
            if i % eval_every == 0:
                every_scale_method = (i // eval_every) % 2 == 1
                flags = ("--methods", "all") if every_scale_method else ()
                code, lines = _eval(folder, workdir / "out", *flags)
                tally["evals"][code] = tally["evals"].get(code, 0) + 1
                errors = [x for x in lines if not x.startswith("companion: warning:")]
                if code not in (0, 2) or (code == 2 and len(errors) != 1):
                    tally["multiline"].append((i, code, lines[:5]))
            else:
                _read_all(folder)
                tally["read"] += 1
        except DatasetError as e:
            tally["refused"] += 1
            if "\n" in str(e):
                tally["multiline"].append((i, str(e)[:300]))
        except HangError:
            tally["hangs"].append(i)
        except BaseException:  # every escape is what the fuzz looks for
            tally["tracebacks"].append((i, traceback.format_exc()[-2000:]))
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        tally["slowest_s"] = max(tally["slowest_s"], time.monotonic() - began)
        tally["cases"] += 1
        shutil.rmtree(folder)
        shutil.rmtree(workdir / "out", ignore_errors=True)
    tally["seconds"] = time.monotonic() - start
    tally["peak_rss_mb"] = peak_rss_mb()  # this process's own peak (not its parent's)
    return tally
