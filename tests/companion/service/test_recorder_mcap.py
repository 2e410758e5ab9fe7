"""The flight recorder writing one MCAP file (record.format = "mcap", the default;
drivers/dataset/mcap_writer.py), read back by the `mcap` library and by our reader.

- every channel has a schema; each JSON message validates against its channel's JSON schema,
  each protobuf message decodes with the schema the file carries; one image per frame, one
  pose per pose sent; the calibration and the config attached; metadata at start and end;
- a recording of a real clip (colour frames, recorded grey) replays to the poses sent, bit for
  bit (`companion eval rec.mcap`);
- a recorder killed with SIGKILL leaves a file read up to its last whole chunk;
- grey is exact: OpenCV's BGR2GRAY of a grey image expanded by GRAY2BGR is that grey image.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import jsonschema
import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from peers.clip_recordings import record_clip
from peers.killed_recorder import KILLED_RECORDER

from companion.cli import main
from companion.config import load_config
from companion.drivers.dataset import mcap_schemas as ms
from companion.drivers.dataset import open_dataset, read_poses_csv
from companion.pipeline import Pipeline
from companion.service.recorder import Recorder
from companion.types import AttitudeSample, CameraFrame, ImuSample, PoseEstimate, RangeSample

SMALL = {"camera": {"width": 160, "height": 120}}


def test_grey_survives_the_round_trip_through_three_channels() -> None:
    """Every 8-bit grey level: GRAY2BGR then BGR2GRAY gives it back (the fixed-point weights
    4899 + 9617 + 1868 sum to 2^14), so a grey recording feeds the VO the grey it saw."""
    grey = np.arange(256, dtype=np.uint8).reshape(16, 16)
    back = cv2.cvtColor(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), cv2.COLOR_BGR2GRAY)
    assert np.array_equal(back, grey)
    noise = np.random.default_rng(3).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    seen = cv2.cvtColor(noise, cv2.COLOR_BGR2GRAY)  # what the VO computes from colour
    ok, png = cv2.imencode(".png", seen)
    decoded = cv2.imdecode(png, cv2.IMREAD_COLOR)  # what Dataset.load_frame gives
    assert ok and np.array_equal(cv2.cvtColor(decoded, cv2.COLOR_BGR2GRAY), seen)


def synthetic(n: int, seed: int = 0) -> list[tuple[CameraFrame, list, list, list]]:
    """n frames of noise, each with ranges and attitudes fed out of time order (a late
    sample, a range newer than its frame) and IMU samples on every other frame."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        t = 1_000_000 + k * 33_333
        img = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
        ranges = [
            RangeSample(t - 5_000, 0, float(rng.uniform(1, 9)), 0.1, 40.0, 100),
            RangeSample(t + 2_000, 2, float(rng.uniform(1, 9)), 0.1, 40.0, 87),
        ]
        q = rng.normal(size=4)
        atts = [
            AttitudeSample(t - 1_000, q / np.linalg.norm(q), rng.normal(size=3)),
            AttitudeSample(t - 9_000, q / np.linalg.norm(q), rng.normal(size=3)),
        ]
        imus = [ImuSample(t - 3_000, *rng.normal(0.0, 3.0, (3, 3)))] if k % 2 else []
        out.append((CameraFrame(t, 500 + k, img), ranges, atts, imus))
    return out


def synthetic_poses(n: int, t0_us: int) -> list[PoseEstimate]:
    """n poses one frame apart from ``t0_us``: the first with an unknown velocity (NaN)."""
    rng = np.random.default_rng(5)
    poses = []
    for k in range(n):
        q = rng.normal(size=4)
        v = np.full(3, np.nan) if k == 0 else rng.normal(size=3)
        cov = np.diag(rng.uniform(1e-4, 1e-2, 6))
        p = PoseEstimate(
            t0_us + k * 33_333, rng.normal(size=3), q / np.linalg.norm(q), v, cov, k // 4, 90
        )
        poses.append(p)
    return poses


def record_synthetic(path: Path, n: int = 12, **record: object) -> tuple[Recorder, list, list]:
    """Record ``n`` synthetic frames (frame 2 held) and a pose after each of the last eight
    into the MCAP file ``path``.mcap; the closed Recorder, the inputs and the poses."""
    cfg = load_config(overrides={**SMALL, "record": {"dir": str(path), **record}})
    inputs = synthetic(n)
    poses = synthetic_poses(8, inputs[n - 8][0].time_us)
    status = Pipeline(cfg).status()  # a real PipelineStatus: no scale yet (null)
    with Recorder(cfg.record, cfg).running() as rec:
        for k, (frame, ranges, atts, imus) in enumerate(inputs):
            rec.frame(frame, ranges, atts, imus, held=k == 2)
            rec.pipeline_state(frame.time_us, status, None if k < 3 else -1234.5)
            if k >= n - len(poses):
                rec.pose(poses[k - (n - len(poses))])
        rec.log_line(
            inputs[4][0].time_us, "camera lost: dark frames", "WARNING", "companion.service"
        )
        rec.log_line(inputs[5][0].time_us, "CMP: VO lost", "ERROR", "companion.statustext")
    return rec, inputs, poses


def test_every_channel_has_a_schema_and_every_message_validates_against_it(
    tmp_path: Path,
) -> None:
    rec, inputs, poses = record_synthetic(tmp_path / "rec")
    assert rec.state == "closed" and rec.path == tmp_path / "rec.mcap"
    counts: dict[str, int] = {}
    logs: list[tuple[str, str]] = []
    decoder = DecoderFactory()
    with (tmp_path / "rec.mcap").open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        for channel in summary.channels.values():  # every channel has its schema
            schema = summary.schemas[channel.schema_id]
            want = "protobuf" if channel.topic in ms.PROTOBUF_TOPICS else "jsonschema"
            assert schema.encoding == want, channel.topic
        for schema, channel, message in reader.iter_messages():
            assert schema is not None
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.message_encoding == "json":
                jsonschema.validate(json.loads(message.data), json.loads(schema.data))
            else:  # decodes with the FileDescriptorSet the file carries
                decode = decoder.decoder_for(channel.message_encoding, schema)
                assert decode is not None
                decoded = decode(message.data)
                if channel.topic == ms.LOG:
                    logs.append((decoded.name, type(decoded).Level.Name(decoded.level)))
                stamped = decoded.transforms[0] if channel.topic == ms.TF else decoded
                stamp = stamped.timestamp
                assert stamp.seconds * 10**9 + stamp.nanos == message.log_time
        attached = {a.name: a.data.decode() for a in reader.iter_attachments()}
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    n = len(inputs)
    assert counts[ms.IMAGE] == counts[ms.FRAME] == counts[ms.STATE] == n == rec.status()["frames"]
    assert logs == [("companion.service", "WARNING"), ("companion.statustext", "ERROR")]
    assert counts[ms.POSE] == counts[ms.TF] == counts[ms.PUBLISHED] == len(poses) == 8
    assert counts[ms.RANGE] == counts[ms.ATTITUDE] == 2 * n and counts[ms.IMU] == n // 2
    assert "[camera]" in attached["calibration.toml"] and "[vo]" in attached["config.toml"]
    start, end = metadata["companion-dataset"], metadata["companion-recording-end"]
    assert start["format"] == "companion-dataset" and start["image"] == "grey"
    assert end == {"complete": "true", "frames": str(n), "published": "8", "stop_reason": ""}


def test_an_mcap_recording_reads_back_exactly_in_the_order_it_was_fed(tmp_path: Path) -> None:
    _, inputs, poses = record_synthetic(tmp_path / "rec")
    ds = open_dataset(tmp_path / "rec.mcap")
    assert ds.complete and ds.frames_checked and len(ds) == len(inputs) and not ds.skipped
    expected: list[object] = []
    for k, (frame, ranges, atts, imus) in enumerate(inputs):
        expected += [*atts, *imus, *ranges] + ([] if k == 2 else [frame])
    got = list(ds.events())
    assert len(got) == len(expected)
    for a, b in zip(got, expected, strict=True):
        assert type(a) is type(b)
        if isinstance(b, CameraFrame):
            assert (a.time_us, a.seq) == (b.time_us, b.seq)
            grey = cv2.cvtColor(b.image_bgr, cv2.COLOR_BGR2GRAY)  # recorded grey (auto)
            assert np.array_equal(cv2.cvtColor(a.image_bgr, cv2.COLOR_BGR2GRAY), grey)
        elif isinstance(b, RangeSample):
            assert a == b  # every float exactly
        else:
            assert a.time_us == b.time_us
            for x, y in zip(vars_of(a), vars_of(b), strict=True):
                assert (x is None and y is None) or np.array_equal(x, y)
    assert len(ds.published) == len(poses)
    for p, sent in zip(ds.published, poses, strict=True):
        assert p.time_us == sent.time_us and p.reset_counter == sent.reset_counter
        assert np.array_equal(p.position_ned_m, sent.position_ned_m)
        assert np.array_equal(p.quat_wxyz, sent.quat_wxyz_ned_frd)
        assert np.array_equal(p.velocity_ned_m_s, sent.velocity_ned_m_s, equal_nan=True)


def vars_of(sample: object) -> list[object]:
    """The array fields of an attitude or IMU sample, in order."""
    if isinstance(sample, AttitudeSample):
        return [sample.quat_wxyz, sample.rates_rad_s]
    assert isinstance(sample, ImuSample)
    return [sample.accel_frd_m_s2, sample.gyro_frd_rad_s, sample.mag_frd_gauss]


def test_colour_when_d_pose_reads_it_and_a_sibling_when_the_name_is_taken(
    tmp_path: Path,
) -> None:
    (tmp_path / "rec.mcap").write_bytes(b"an earlier run")
    cfg = load_config(
        overrides={**SMALL, "dpose": {"enabled": True}, "record": {"dir": str(tmp_path / "rec")}}
    )
    frame, ranges, atts, _ = synthetic(1)[0]
    said: list[str] = []
    with Recorder(cfg.record, cfg).running(said.append) as rec:
        rec.frame(frame, ranges, atts)
    assert rec.path == tmp_path / "rec-2.mcap" and len(said) == 1 and "rec-2.mcap" in said[0]
    assert (tmp_path / "rec.mcap").read_bytes() == b"an earlier run"
    ds = open_dataset(rec.path)
    assert ds.meta["image"] == "colour"
    assert np.array_equal(ds.load_frame(0).image_bgr, frame.image_bgr)  # colour, lossless


def test_a_recorded_clip_replays_bit_for_bit_from_the_mcap_file(tmp_path: Path) -> None:
    """The MCAP twin of test_a_recorded_sitl_flight_replays_to_the_published_poses: colour
    frames recorded grey, `companion eval rec.mcap` gives every pose sent, equal in every
    bit (position, attitude, velocity)."""
    rec, sent = record_clip(tmp_path / "rec", frames=60)
    assert rec.state == "closed" and len(sent) >= 40
    out = tmp_path / "replay"
    assert main(["eval", str(tmp_path / "rec.mcap"), "--out", str(out), "--no-progress"]) == 0
    replayed = {p.time_us: p for p in read_poses_csv(out / "poses.csv")}
    assert len(replayed) == len(sent)
    for pose in sent:
        mine = replayed[pose.time_us]
        assert np.array_equal(mine.position_ned_m, pose.position_ned_m)
        assert np.array_equal(mine.quat_wxyz, pose.quat_wxyz_ned_frd)
        assert np.array_equal(mine.velocity_ned_m_s, pose.velocity_ned_m_s, equal_nan=True)
    check = json.loads((out / "replay.json").read_text())
    assert check["matched"] == check["published"] == len(sent)
    assert check["max_position_diff_m"] == 0.0


def test_sigkill_leaves_an_mcap_file_readable_to_its_last_whole_chunk(tmp_path: Path) -> None:
    """Killed with SIGKILL after more than a chunk (4 MB: about 50 of these noise frames) and
    a sync: the file has no footer; the reader takes every whole chunk, stops cleanly at the
    torn tail and says the recording is not complete."""
    path = tmp_path / "rec.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", KILLED_RECORDER, str(tmp_path / "rec"), "mcap"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "recording"
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and path.stat().st_size < 6e6:
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(10)
    ds = open_dataset(path)
    assert not ds.complete and len(ds) >= 20
    assert [ds.load_frame(k).seq for k in range(len(ds))] == list(range(len(ds)))
    assert [r.distance_m for r in ds.ranges] == [3.0 + i * 1e-3 for i in range(len(ds))]
    assert len(ds.attitudes) == len(ds)
    size = path.stat().st_size
    with path.open("ab") as fh:  # a torn chunk after it: the same frames
        fh.write(b"\x06" + (10**6).to_bytes(8, "little") + b"torn")
    again = open_dataset(path)
    assert len(again) == len(ds) and not again.complete and size < path.stat().st_size


def test_the_disk_budget_closes_a_valid_mcap_file_that_says_why(tmp_path: Path) -> None:
    said: list[str] = []
    cfg = load_config(overrides={**SMALL, "record": {"dir": str(tmp_path / "rec"), "max_mb": 0.3}})
    inputs = synthetic(40)  # about 20 kB per grey PNG of noise: the budget holds about 14
    with Recorder(cfg.record, cfg).running(said.append) as rec:
        for frame, ranges, atts, imus in inputs:
            rec.frame(frame, ranges, atts, imus)
    assert rec.state == "stopped" and "record.max_mb" in rec.reason and len(said) == 1
    assert (tmp_path / "rec.mcap").stat().st_size <= 0.3e6
    ds = open_dataset(tmp_path / "rec.mcap")
    assert ds.complete and ds.meta["stop_reason"] == rec.reason
    assert 5 <= len(ds) < 40 and rec.frames_not_recorded == 40 - len(ds)
    with (tmp_path / "rec.mcap").open("rb") as fh:  # the reason on /log, for the viewers
        logs = [m.data for _, c, m in make_reader(fh).iter_messages() if c.topic == ms.LOG]
    assert len(logs) == 1 and b"record.max_mb" in logs[0]
