"""Small valid datasets (a recording of ours, a EuRoC folder) held as bytes, and the hostile or
damaged variants of them that tests/test_hostile_inputs.py and tests/test_fuzz_dataset.py feed
to the reader and to `companion eval`: files outside the folder, FIFOs, decompression bombs,
deep TOML, bad numbers, zero quaternions, torn and reordered rows, random byte flips."""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from companion.config import load_config
from companion.types import AttitudeSample, CameraFrame, ImuSample, PoseEstimate, RangeSample
from drivers.dataset import DatasetWriter

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
