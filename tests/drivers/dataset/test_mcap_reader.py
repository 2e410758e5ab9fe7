"""MCAP recordings from anywhere (drivers/dataset/mcap_records.py, mcap_reader.py): a torn,
truncated, damaged, oversized or foreign file is a DatasetError naming the file, or a
recording read up to its last whole chunk; never a traceback, never an allocation the file
merely claims."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.writer import Writer

from companion.config import Config, load_config
from companion.drivers.dataset import mcap_schemas as ms
from companion.drivers.dataset import open_dataset
from companion.drivers.dataset.mcap_writer import McapDatasetWriter
from companion.errors import DatasetError
from companion.types import AttitudeSample, CameraFrame, RangeSample

SMALL = {"camera": {"width": 160, "height": 120}}


def small_config() -> Config:
    return load_config(overrides=SMALL)


def write(path: Path, frames: int = 30, chunk_bytes: int = 64 << 10, close: bool = True) -> None:
    """``frames`` frames of seeded noise (about 20 kB each as grey PNG: a chunk per 3) with a
    range and an attitude each; closed or left as a killed writer leaves it."""
    rng = np.random.default_rng(2)
    w = McapDatasetWriter(path, small_config(), chunk_bytes=chunk_bytes)
    for k in range(frames):
        t = 1_000_000 + 33_333 * k
        img = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
        ranges = [RangeSample(t - 10, 0, 2.0 + k, 0.1, 40.0, 100)]
        atts = [AttitudeSample(t - 20, np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3))]
        w.write_frame(CameraFrame(t, k, img), w.encode(img), ranges, atts)
    if close:
        w.close()
    else:
        w.sync()  # what the recorder does once a second; then the process dies
        w._file.close()


def test_every_truncation_reads_whole_chunks_or_names_the_file(tmp_path: Path) -> None:
    whole = tmp_path / "whole.mcap"
    write(whole)
    data = whole.read_bytes()
    full = open_dataset(whole)
    assert full.complete and len(full) == 30
    seen = set()
    for cut in np.linspace(0, len(data) - 1, 41).astype(int):
        part = tmp_path / f"cut{cut}.mcap"
        part.write_bytes(data[:cut])
        try:
            ds = open_dataset(part)
        except DatasetError as e:
            assert str(part) in str(e)
            continue
        assert not ds.complete and len(ds) <= 30
        seen.add(len(ds))
        for k in range(len(ds)):  # every frame it has is whole, with its sample
            assert np.array_equal(ds.load_frame(k).image_bgr, full.load_frame(k).image_bgr)
        assert [r.distance_m for r in ds.ranges] == [2.0 + k for k in range(len(ds))]
    assert len(seen) >= 5  # the cuts fall between chunks: more frames as the file grows


def test_an_unclosed_file_is_read_to_its_last_chunk(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    write(path, close=False)
    ds = open_dataset(path)
    assert not ds.complete and len(ds) == 30 and len(ds.attitudes) == 30


@pytest.mark.parametrize(
    "content, says",
    [
        (b"", "not an MCAP file"),
        (b"PK\x03\x04 a zip file, not a recording" * 10, "not an MCAP file"),
        (bytes(range(256)) * 64, "not an MCAP file"),
    ],
)
def test_a_file_that_is_no_recording_is_refused_by_name(
    tmp_path: Path, content: bytes, says: str
) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    with pytest.raises(DatasetError, match=says) as e:
        open_dataset(path)
    assert str(path) in str(e.value)


def test_an_mcap_file_of_someone_else_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "other.mcap"
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start()
        schema = w.register_schema("x", "jsonschema", b"{}")
        channel = w.register_channel("/companion/frame", "json", schema)
        w.add_message(channel, 1, b'{"index": 0}', 1)
        w.finish()
    with pytest.raises(DatasetError, match="not a companion-dataset MCAP recording"):
        open_dataset(path)


def first_chunk(data: bytes) -> int:
    """The file offset of the first chunk record (walking the records from the magic)."""
    pos = 8
    while data[pos] != 0x06:
        pos += 9 + int.from_bytes(data[pos + 1 : pos + 9], "little")
    return pos


def test_damage_inside_a_closed_file_is_refused_and_a_huge_claim_is_not_allocated(
    tmp_path: Path,
) -> None:
    path = tmp_path / "rec.mcap"
    write(path)
    data = bytearray(path.read_bytes())
    chunk = data.index(b"zstd")  # inside the first chunk's compressed records
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data[: chunk + 40]) + b"\x00" * 8 + bytes(data[chunk + 48 :]))
    with pytest.raises(DatasetError, match="damaged MCAP file") as e:
        open_dataset(damaged)
    assert str(damaged) in str(e.value)
    # a record header claiming 2^60 bytes, in a closed file and in an unclosed one
    huge = b"\x06" + (1 << 60).to_bytes(8, "little")
    first = first_chunk(bytes(data))
    lying = tmp_path / "lying.mcap"
    lying.write_bytes(bytes(data[:first]) + huge + bytes(data[first + 9 :]))
    with pytest.raises(DatasetError, match="more than"):
        open_dataset(lying)
    lying.write_bytes(bytes(data[:first]) + huge)  # never closed: nothing after it
    ds = open_dataset(lying)
    assert not ds.complete and len(ds) == 0


def test_bad_messages_are_counted_and_bad_images_named(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    w = McapDatasetWriter(path, small_config())
    t = 1_000_000
    w._add(ms.RANGE, t, b'{"time_us": 1, "sensor_id": 0, "distance_m": NaN}')
    w._add(ms.RANGE, t, b"[" * 100_000)  # deeper than JSON may nest here
    w._add(ms.ATTITUDE, t, b'{"time_us": 1, "quat_wxyz": [0, 0, 0, 0], "rates_rad_s": [0,0,0]}')
    tiny = cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes()
    w.write_frame(CameraFrame(t, 0, np.zeros((0, 0, 3), np.uint8)), tiny, [], [])
    w._add(ms.IMAGE, t + 1, ms.image_message(t + 1, b"RIFF....WEBP", "webp"))
    w._add(ms.FRAME, t + 1, ms.frame_json(1, t + 1, 1, False))
    w.close()
    ds = open_dataset(path)
    assert len(ds) == 2 and not ds.ranges and not ds.attitudes
    assert ds.skipped[ms.RANGE].skipped == 2 and ds.skipped[ms.ATTITUDE].skipped == 1
    assert "not a JSON number" in ds.skipped[ms.RANGE].first
    with pytest.raises(DatasetError, match=r"8 x 8 px.*160 x 120"):
        ds.load_frame(0)
    with pytest.raises(DatasetError, match="'webp'"):
        ds.load_frame(1)


def test_frames_out_of_order_in_a_closed_file_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    w = McapDatasetWriter(path, small_config())
    img = np.zeros((120, 160), np.uint8)
    img[::7] = 200
    for index in (0, 0):  # the second frame record repeats index 0
        w._add(ms.IMAGE, 1000, ms.image_message(1000, w.encode(img), "png"))
        w._add(ms.FRAME, 1000, ms.frame_json(index, 1000 + index, 0, False))
    w.close()
    with pytest.raises(DatasetError, match="frame record 1"):
        open_dataset(path)


def test_a_fifo_or_a_link_is_not_opened(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.mcap"
    os.mkfifo(fifo)
    with pytest.raises(DatasetError, match="FIFO"):
        open_dataset(fifo)  # at once, not blocked waiting for a writer
    write(tmp_path / "real.mcap", frames=2)
    (tmp_path / "link.mcap").symlink_to(tmp_path / "real.mcap")
    with pytest.raises(DatasetError, match="cannot read"):
        open_dataset(tmp_path / "link.mcap")


def test_random_damage_is_a_dataset_error_or_a_readable_recording(tmp_path: Path) -> None:
    """Seeded fuzzing: bytes overwritten anywhere (headers, lengths, compressed chunks, the
    summary), closed and unclosed: opening and loading every frame ends in a DatasetError or
    a dataset, nothing else (no traceback of another kind, no huge allocation)."""
    path = tmp_path / "rec.mcap"
    write(path, frames=6, chunk_bytes=16 << 10)
    data = path.read_bytes()
    rng = np.random.default_rng(11)
    outcomes = {"refused": 0, "read": 0}
    for trial in range(150):
        bad = bytearray(data if trial % 3 else data[: int(rng.integers(8, len(data)))])
        for _ in range(int(rng.integers(1, 4))):
            at = int(rng.integers(0, len(bad)))
            bad[at : at + 8] = rng.integers(0, 256, 8, dtype=np.uint8).tobytes()
        fuzzed = tmp_path / f"f{trial}.mcap"
        fuzzed.write_bytes(bytes(bad))
        try:
            ds = open_dataset(fuzzed)
            for k in range(len(ds)):
                with contextlib.suppress(DatasetError):
                    ds.load_frame(k)
            outcomes["read"] += 1
        except DatasetError as e:
            assert str(fuzzed) in str(e)
            outcomes["refused"] += 1
        fuzzed.unlink()
    assert outcomes["refused"] > 10 and outcomes["read"] > 10, outcomes
