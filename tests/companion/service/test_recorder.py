"""The flight recorder (companion/service/recorder.py, drivers.dataset.DatasetWriter).

- a recorded SITL flight through the running service replays (``companion eval DIR``) to the
  poses the service published, to 1e-9;
- what is written reads back exactly (PNG images, floats, the order of ingestion);
- the disk budget and a full queue stop the recording, not the caller, and leave a valid
  dataset; a recorder killed with SIGKILL leaves one readable to its last complete frame;
- a bad record.dir is a config error (exit 2).
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from peers import sitl_flight
from peers.killed_recorder import KILLED_RECORDER

from companion.cli import main
from companion.config import Config, load_config
from companion.drivers.dataset import DatasetWriter, open_dataset, read_poses_csv
from companion.service.recorder import Recorder, recording_dir
from companion.types import AttitudeSample, CameraFrame, ImuSample, RangeSample

FLIGHT_S = float(os.environ.get("COMPANION_RECORDER_SECONDS", "14"))


def with_record(cfg: Config, folder: Path, **options: object) -> Config:
    """``cfg`` recording into ``folder`` (a folder recording unless ``format`` says else)."""
    options = {"format": "folder", **options}
    return dataclasses.replace(
        cfg, record=dataclasses.replace(cfg.record, dir=str(folder), **options)
    )


SYNTHETIC_CAMERA = {"camera": {"width": 160, "height": 120}}  # the size of synthetic_inputs' frames


def synthetic_inputs(n: int, seed: int = 0) -> list[tuple[CameraFrame, list, list]]:
    """n frames of noise with ranges and attitudes, some fed out of time order (a late
    sample, a range newer than its frame) as a real link can deliver them."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        t = 1_000_000 + k * 33_333
        img = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
        ranges = [
            RangeSample(t - 5_000, 0, float(rng.uniform(1, 9)), 0.1, 40.0, 100),
            RangeSample(t + 2_000, 2, float(rng.uniform(1, 9)), 0.1, 40.0, 87),  # after it
        ]
        q = rng.normal(size=4)
        atts = [
            AttitudeSample(t - 1_000, q / np.linalg.norm(q), rng.normal(size=3)),
            AttitudeSample(t - 9_000, q / np.linalg.norm(q), rng.normal(size=3)),  # late
        ]
        out.append((CameraFrame(t, 500 + k, img), ranges, atts))
    return out


def test_recording_reads_back_exactly_in_the_order_it_was_fed(tmp_path: Path) -> None:
    cfg = with_record(load_config(overrides=SYNTHETIC_CAMERA), tmp_path / "rec")
    inputs = synthetic_inputs(12)
    rng = np.random.default_rng(7)
    imus = [  # SCALED_IMU samples for all but the first frame: one with the gyroscope and the
        # magnetometer, one with the accelerometer alone (an autopilot without a compass)
        [
            ImuSample(f.time_us - 30_000, *rng.normal(0.0, 3.0, (3, 3))),
            ImuSample(f.time_us - 10_000, rng.normal(0.0, 3.0, 3)),
        ]
        if k
        else []
        for k, (f, _, _) in enumerate(inputs)
    ]
    held = {1, 2}  # frames the service held from its VO (waiting for the autopilot's attitude)
    with Recorder(cfg.record, cfg).running() as rec:
        for k, ((frame, ranges, atts), imu) in enumerate(zip(inputs, imus, strict=True)):
            rec.frame(frame, ranges, atts, imu, k in held)
    assert rec.state == "closed" and rec.status()["frames"] == 12
    ds = open_dataset(tmp_path / "rec")
    assert ds.complete and ds.frames_checked and not ds.has_world and ds.sitl is None
    assert [r.sensor_id for r in ds.rangefinders] == [r.sensor_id for r in cfg.rangefinders]
    assert ds.config is not None and ds.config.vo == cfg.vo and ds.config.scale == cfg.scale
    expected: list[object] = []
    for k, ((frame, ranges, atts), imu) in enumerate(zip(inputs, imus, strict=True)):
        # a held frame's samples were fed, the frame was not: a replay does the same
        expected += [*atts, *imu, *ranges] + ([] if k in held else [frame])
    got = list(ds.events())
    assert len(got) == len(expected)
    for a, b in zip(got, expected, strict=True):
        assert type(a) is type(b)
        if isinstance(b, CameraFrame):
            assert (a.time_us, a.seq) == (b.time_us, b.seq)
            assert np.array_equal(a.image_bgr, b.image_bgr)  # PNG: lossless
        elif isinstance(b, RangeSample):
            assert a == b  # every float exactly
        elif isinstance(b, ImuSample):
            assert a.time_us == b.time_us
            assert np.array_equal(a.accel_frd_m_s2, b.accel_frd_m_s2)
            for read, fed in (
                (a.gyro_frd_rad_s, b.gyro_frd_rad_s),
                (a.mag_frd_gauss, b.mag_frd_gauss),
            ):
                assert (read is None and fed is None) or np.array_equal(read, fed)
        else:
            assert a.time_us == b.time_us
            assert np.array_equal(a.quat_wxyz, b.quat_wxyz)
            assert np.array_equal(a.rates_rad_s, b.rates_rad_s)


def test_disk_budget_stops_recording_cleanly(tmp_path: Path) -> None:
    said: list[str] = []
    cfg = with_record(
        load_config(overrides=SYNTHETIC_CAMERA), tmp_path / "rec", max_mb=0.5, png_compression=0
    )
    inputs = synthetic_inputs(40)  # 58 kB per uncompressed PNG: the budget holds about 8
    with Recorder(cfg.record, cfg).running(said.append) as rec:
        for frame, ranges, atts in inputs:
            rec.frame(frame, ranges, atts)
    assert rec.state == "stopped" and "budget of 0.5 MB" in rec.reason
    assert len(said) == 1 and "record.max_mb" in said[0]
    size = sum(p.stat().st_size for p in (tmp_path / "rec").rglob("*") if p.is_file())
    assert size <= 0.5e6
    ds = open_dataset(tmp_path / "rec")
    assert ds.complete and ds.meta["stop_reason"] == rec.reason
    assert 3 <= len(ds) < 40 and len(ds) == rec.status()["frames"]
    assert rec.frames_not_recorded == 40 - len(ds)
    for k in range(len(ds)):  # every frame it holds is whole, with its samples
        assert np.array_equal(ds.load_frame(k).image_bgr, inputs[k][0].image_bgr)
    assert len(ds.ranges) == 2 * len(ds) and len(ds.attitudes) == 2 * len(ds)


def test_a_full_queue_stops_the_recording_never_the_caller(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A disk that stalls: the writer blocks in its first write; the producer keeps going
    (every call returns), the recording stops once the queue is full, and what was queued
    before is still written when the disk comes back."""
    disk, writing = threading.Event(), threading.Event()
    real = DatasetWriter.write_frame

    def stalled(self: DatasetWriter, *a: object) -> None:
        writing.set()
        disk.wait(60)
        real(self, *a)  # type: ignore[arg-type]

    monkeypatch.setattr(DatasetWriter, "write_frame", stalled)
    said: list[str] = []
    cfg = with_record(load_config(overrides=SYNTHETIC_CAMERA), tmp_path / "rec", queue_frames=4)
    inputs = synthetic_inputs(20)
    rec = Recorder(cfg.record, cfg).running(said.append)
    rec.frame(*inputs[0])
    assert writing.wait(30)  # the writer holds frame 0, the disk does not answer
    for frame, ranges, atts in inputs[1:]:
        rec.frame(frame, ranges, atts)  # never waits for the disk
    assert rec.state == "stopped" and "slower than the camera" in rec.reason
    assert len(said) == 1
    disk.set()
    rec.close()
    ds = open_dataset(tmp_path / "rec")
    # one frame in the writer's hands, four in the queue; the sixth did not fit
    assert ds.complete and len(ds) == 5
    assert [f.seq for f in ds.frames()] == [500, 501, 502, 503, 504]
    assert rec.frames_not_recorded == 15


def test_sigkill_leaves_a_recording_readable_to_its_last_complete_frame(tmp_path: Path) -> None:
    rec = tmp_path / "rec"
    proc = subprocess.Popen(
        [sys.executable, "-c", KILLED_RECORDER, str(rec), "folder"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "recording"
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # at least a few frames on disk
            rows = (rec / "frames.csv").read_text().count("\n") if rec.exists() else 0
            if rows > 6:
                break
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(10)
    ds = open_dataset(rec)
    assert not ds.complete and len(ds) >= 5
    assert (rec / "images" / f"{len(ds) - 1:06d}.png").exists()
    for k in range(len(ds)):
        assert ds.load_frame(k).seq == k
    assert all(r.distance_m == 3.0 + i * 1e-3 for i, r in enumerate(ds.ranges))
    assert len(ds.ranges) == len(ds) and len(ds.attitudes) == len(ds)
    # a writer killed inside a row: the torn rows and the frame without its image go
    n = len(ds)
    # the kill may land between a frame's image and its row: that image is an orphan
    (rec / "images" / f"{n:06d}.png").unlink(missing_ok=True)
    with (rec / "ranges.csv").open("a") as fh:
        fh.write(f"2000000,1,3.5,0.1,40.0,10,{n}")  # no newline: torn
    with (rec / "frames.csv").open("a") as fh:
        fh.write(f"2000000,{n},images/{n:06d}.png\n2000100,{n + 1},ima")
    again = open_dataset(rec)
    assert len(again) == n and len(again.ranges) == n


def test_a_used_record_dir_records_into_a_new_sibling_and_says_so(tmp_path: Path) -> None:
    """record.dir without {start} after a reboot: the earlier run's folder is left as it is,
    the recording goes into rec-2 (then rec-3), and the operator is told where."""
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "meta.toml").write_text("earlier run")
    cfg = with_record(load_config(overrides=SYNTHETIC_CAMERA), rec)
    frame, ranges, atts = synthetic_inputs(1)[0]
    for sibling in ("rec-2", "rec-3"):
        said: list[str] = []
        with Recorder(cfg.record, cfg).running(said.append) as recorder:
            recorder.frame(frame, ranges, atts)
        assert recorder.path == tmp_path / sibling and recorder.state == "closed"
        assert len(said) == 1 and f"recording into {tmp_path / sibling}" in said[0]
        assert len(open_dataset(tmp_path / sibling)) == 1
        assert recorder.status()["dir"] == str(tmp_path / sibling)
    assert [p.name for p in rec.iterdir()] == ["meta.toml"]
    assert (rec / "meta.toml").read_text() == "earlier run"
    start = time.strptime("2026-05-01 12:30:05", "%Y-%m-%d %H:%M:%S")
    assert recording_dir("/x/flight-{start}", start) == Path("/x/flight-20260501-123005")


def plant_links(folder: Path, outside: Path) -> dict[Path, bytes]:
    """Symbolic links from the names a recording writes to files and a folder in
    ``outside``; returns the outside files with their content (to check they are intact)."""
    outside.mkdir(exist_ok=True)
    victims: dict[Path, bytes] = {}
    for name in ("meta.toml", "calibration.toml", "frames.csv", "published.csv"):
        victim = outside / f"victim-{name}"
        victim.write_bytes(b"not yours\n")
        victims[victim] = victim.read_bytes()
        (folder / name).symlink_to(victim)
    (outside / "images").mkdir()
    (folder / "images").symlink_to(outside / "images")
    return victims


def test_planted_links_never_make_the_recorder_write_outside_its_folder(tmp_path: Path) -> None:
    """The service runs as root: links planted in a pre-made record.dir, or a record.dir that
    is itself a link to another (empty) folder, must not make it write anywhere else."""
    outside = tmp_path / "outside"
    used = tmp_path / "used"
    used.mkdir()
    victims = plant_links(used, outside)
    (outside / "empty").mkdir()
    (tmp_path / "linked").symlink_to(outside / "empty")
    frame, ranges, atts = synthetic_inputs(1)[0]
    for folder in (used, tmp_path / "linked"):
        cfg = with_record(load_config(overrides=SYNTHETIC_CAMERA), folder)
        said: list[str] = []
        with Recorder(cfg.record, cfg).running(said.append) as recorder:
            recorder.frame(frame, ranges, atts)
        assert recorder.path == tmp_path / f"{folder.name}-2" and recorder.state == "closed"
        assert len(open_dataset(recorder.path)) == 1 and len(said) == 1
    assert {v: v.read_bytes() for v in victims} == victims
    assert not any((outside / "images").iterdir()) and not any((outside / "empty").iterdir())


def test_the_dataset_writer_creates_its_files_never_through_a_link(tmp_path: Path) -> None:
    """A link that appears in the recording's folder after it was made (a race): the write
    fails (the recorder stops, the service runs on); the link's target is untouched."""
    victim = tmp_path / "victim"
    victim.write_bytes(b"not yours\n")
    writer = DatasetWriter(tmp_path / "rec", load_config(overrides=SYNTHETIC_CAMERA))
    (tmp_path / "rec" / "images" / "000000.png").symlink_to(victim)
    frame, ranges, atts = synthetic_inputs(1)[0]
    with pytest.raises(FileExistsError):
        writer.write_frame(frame, writer.encode(frame.image_bgr), ranges, atts)
    writer.close()
    assert victim.read_bytes() == b"not yours\n"


# ------------------------------------------------------------------------------ round trip
def fly_recording(tmp_path: Path, **record: object) -> Any:
    """The service with the recorder into tmp_path/rec ([record] options ``record``) on a
    SITL flight of FLIGHT_S seconds against the SITL autopilot (peers.sitl_flight); returns
    the service after the flight."""
    from companion.service.app import Service
    from companion.sitl.stub.autopilot import SimAutopilot

    cfg, opts = sitl_flight(tmp_path, FLIGHT_S, small=True)  # the 320x240 camera
    cfg = with_record(cfg, tmp_path / "rec", **record)

    async def fly() -> Service:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(tmp_path / "autopilot"))
        async with Service(cfg) as service:
            stub_task.add_done_callback(lambda _: service.stop())
            await service.run()
        await stub_task
        return service

    return asyncio.run(fly())


def same(a: np.ndarray, b: np.ndarray) -> None:
    """Equal to 1e-9; NaN (unknown) only against NaN."""
    np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9, equal_nan=True)


@pytest.mark.slow
@pytest.mark.timeout(4 * FLIGHT_S + 300)
def test_a_recorded_sitl_flight_replays_to_the_published_poses(tmp_path: Path) -> None:
    """The service flies the SITL stub with --record (the default: one MCAP file); the file,
    read with the `mcap` library, has a valid schema for every message, an image per frame
    the pipeline took, a pose per pose sent, the pipeline's state per frame and the
    STATUSTEXT lines sent; `companion eval rec.mcap` replays it through a fresh Pipeline:
    every pose the service sent comes out again, equal to 1e-9 (the pipeline is deterministic
    given the same inputs in the same order, and the recording keeps both: lossless frames,
    exact floats, the order of ingestion)."""
    # room for the whole flight in the writer's queue: on a machine loaded by other work the
    # (niced) writer may fall far behind, and back-pressure has its own test above
    service = fly_recording(tmp_path, format="mcap", queue_frames=int(FLIGHT_S * 30) + 60)
    summary = service.summary()
    assert summary["pipeline_errors"] == 0
    assert summary["recorder"]["state"] == "closed", summary["recorder"]
    sent = list(service.stats.sent)  # the last 200 poses sent, as the service held them
    assert summary["published"] >= 100 and len(sent) >= 100

    rec = tmp_path / "rec.mcap"
    counts, logs, offsets = read_mcap_validated(rec)
    assert counts["/camera/image"] == counts["/companion/frame"] == summary["frames_processed"]
    assert counts["/companion/state"] == summary["frames_processed"]
    assert counts["/pose"] == counts["/companion/published"] == summary["published"]
    statustexts = [text for name, text in logs if name == "companion.statustext"]
    said = [t for _, t in service.stats.statustexts]  # the last words come after the close
    assert statustexts and statustexts == said[: len(statustexts)], (statustexts, said)
    assert offsets[-1] is not None  # the stub answers TIMESYNC: its clock's offset is known
    ds = open_dataset(rec)
    assert ds.complete and len(ds) == summary["frames_processed"]
    published = ds.published
    assert len(published) == summary["published"]

    out = tmp_path / "replay"
    assert main(["eval", str(rec), "--out", str(out), "--no-progress"]) == 0
    replayed = {p.time_us: p for p in read_poses_csv(out / "poses.csv")}

    for pose in sent:  # against the service's own poses (float64, in memory)
        mine = replayed[pose.time_us]
        same(mine.position_ned_m, pose.position_ned_m)
        same(mine.quat_wxyz, pose.quat_wxyz_ned_frd)
        same(mine.velocity_ned_m_s, pose.velocity_ned_m_s)
    for p in published:  # and every pose of the flight, as recorded
        mine = replayed[p.time_us]
        same(mine.position_ned_m, p.position_ned_m)
        same(mine.quat_wxyz, p.quat_wxyz)
        same(mine.velocity_ned_m_s, p.velocity_ned_m_s)
    check = json.loads((out / "replay.json").read_text())
    assert check["matched"] == check["published"] == len(published)
    assert check["max_position_diff_m"] <= 1e-9 and check["max_angle_diff_rad"] <= 1e-6


def read_mcap_validated(
    path: Path,
) -> tuple[dict[str, int], list[tuple[str, str]], list[float | None]]:
    """An MCAP recording read with the `mcap` library, each JSON message validated against
    its channel's JSON schema and each protobuf one decoded with the schema the file carries:
    the messages per topic, the /log lines (name, text) and /companion/state's clock offsets."""
    counts: dict[str, int] = {}
    logs: list[tuple[str, str]] = []
    offsets: list[float | None] = []
    decoder = DecoderFactory()
    with path.open("rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            assert schema is not None, channel.topic
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.message_encoding == "json":
                data = json.loads(message.data)
                jsonschema.validate(data, json.loads(schema.data))
                if channel.topic == "/companion/state":
                    offsets.append(data["autopilot_offset_us"])
                continue
            decode = decoder.decoder_for(channel.message_encoding, schema)
            assert decode is not None, channel.topic
            decoded = decode(message.data)
            if channel.topic == "/log":
                logs.append((decoded.name, decoded.message))
    return counts, logs, offsets


@pytest.mark.slow
@pytest.mark.timeout(4 * FLIGHT_S + 300)
def test_the_disk_budget_ends_the_recording_mid_flight_not_the_output(tmp_path: Path) -> None:
    """A budget of about a third of the flight: the recording stops cleanly (said in the
    service's warnings and status), the service keeps publishing after it, and the recording
    replays exactly up to its last frame."""
    budget_mb = 0.185 * 30 * FLIGHT_S / 3  # PNG frames of the 320x240 camera: ~0.185 MB each
    service = fly_recording(tmp_path, max_mb=budget_mb, queue_frames=int(FLIGHT_S * 30) + 60)
    summary = service.summary()
    rec = summary["recorder"]
    assert rec["state"] == "stopped" and "record.max_mb" in rec["reason"], rec
    assert any("recorder: stopped" in w and "record.max_mb" in w for w in summary["warnings"])
    ds = open_dataset(tmp_path / "rec")
    assert ds.complete and ds.meta["stop_reason"] == rec["reason"]
    assert 0 < len(ds) < summary["frames_processed"] and rec["mb"] <= budget_mb
    last_us = int(ds.frame_times_us[-1])
    after = [p for p in service.stats.sent if p.time_us > last_us]
    assert len(after) >= 100  # the output went on after the recording stopped
    out = tmp_path / "replay"
    assert main(["eval", str(tmp_path / "rec"), "--out", str(out), "--no-progress"]) == 0
    replayed = {p.time_us: p for p in read_poses_csv(out / "poses.csv")}
    published = read_poses_csv(tmp_path / "rec" / "published.csv")
    assert published and all(p.time_us <= last_us for p in published)
    for p in published:
        same(replayed[p.time_us].position_ned_m, p.position_ned_m)
        same(replayed[p.time_us].quat_wxyz, p.quat_wxyz)


def test_atomic_write_never_writes_through_a_planted_temporary_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """meta.toml (and the state files) go through atomic_write: a link planted at the
    temporary name it used to take (pid-based: predictable) is not followed, and neither is
    one at a name it draws (the next random name is taken instead)."""
    import secrets

    from companion.drivers import files

    victim = tmp_path / "victim"
    victim.write_bytes(b"not yours\n")
    target = tmp_path / "meta.toml"
    (tmp_path / f".meta.toml.{os.getpid()}.tmp").symlink_to(victim)
    drawn = iter(["planted", "planted", "free"])
    (tmp_path / ".meta.toml.planted.tmp").symlink_to(victim)
    monkeypatch.setattr(secrets, "token_hex", lambda _n: next(drawn))
    files.atomic_write(target, b"complete = true\n")
    assert target.read_bytes() == b"complete = true\n" and not target.is_symlink()
    assert victim.read_bytes() == b"not yours\n"
    assert not (tmp_path / ".meta.toml.free.tmp").exists()
    monkeypatch.undo()
    target.unlink()
    target.symlink_to(victim)  # a link at the target itself is replaced, not followed
    files.atomic_write(target, b"new\n")
    assert target.read_bytes() == b"new\n" and victim.read_bytes() == b"not yours\n"
