"""Read an MCAP flight recording (``McapDatasetWriter``'s; docs/dataset.md, "MCAP
recordings") as a :class:`Dataset`, the same one a folder recording gives: frames, the
samples in the order they were fed, the held flags, the published poses, the calibration
and algorithm options from the attachments, and ``complete``.

The file is read once at open (every chunk decompressed, the JSON samples parsed and checked
as a folder's CSV rows are); the images stay in the file: each frame keeps its image's place
(chunk and offset), and ``Dataset.load_frame`` reads it back when asked (the last chunk
cached: a replay in order decompresses each chunk once more).

A file that was never closed (no MCAP magic at its end: the recorder was killed, the power
cut) is read up to its first torn or malformed record and is ``complete = False``: a frame
counts once its frame record was read (after its image and its samples). A closed file with
a bad record, a file without our metadata, a frame record out of order and an image that
is not a PNG or JPEG of the calibration's size are a DatasetError naming the file; a sample
that does not parse is left out and counted (``Dataset.skipped``), as a CSV row would be.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from google.protobuf.message import DecodeError

from companion.drivers.dataset import mcap_schemas as ms
from companion.drivers.dataset.format import (
    FORMAT_NAME,
    MAX_DISTANCE_M,
    MAX_MAGNETIC_GAUSS,
    MAX_POSITION_M,
    MAX_RATE_RAD_S,
    MAX_SEQ,
    MAX_SPECIFIC_FORCE_M_S2,
    MAX_TIME_US,
    MAX_VELOCITY_M_S,
    QUAT_NORM_TOLERANCE,
    PublishedPose,
    RowCount,
)
from companion.drivers.dataset.mcap_records import (
    Record,
    TornError,
    Where,
    closed_file,
    open_regular,
    read_at,
    scan,
)
from companion.drivers.dataset.mcap_writer import END_NAME, META_NAME
from companion.drivers.dataset.model import Dataset, check_lens
from companion.drivers.dataset.ours import config_from_tables
from companion.drivers.safe_files import MAX_IMAGE_BYTES, MAX_TOML_BYTES
from companion.errors import DatasetError
from companion.toml_files import decode_utf8, parse_toml
from companion.types import F64, AttitudeSample, ImuSample, RangeSample

MAX_JSON_BYTES = 64 << 10  # one sample or frame record (ours: about 200 bytes)
ENCODINGS = {**{t: "protobuf" for t in ms.PROTOBUF_TOPICS}, **{t: "json" for t in ms.SCHEMAS}}
ATTACHED = ("calibration.toml", "config.toml")


class _BadMessageError(Exception):
    """A message whose content is not what its channel's schema says."""


def _reject(name: str) -> Any:
    raise _BadMessageError(f"{name} is not a JSON number")


def _object(data: bytes) -> dict[str, Any]:
    if len(data) > MAX_JSON_BYTES:
        raise _BadMessageError(f"{len(data)} bytes (more than {MAX_JSON_BYTES})")
    try:
        obj = json.loads(data, parse_constant=_reject)
    except (ValueError, RecursionError) as e:
        raise _BadMessageError(f"not JSON ({str(e)[:60]})") from None
    if not isinstance(obj, dict):
        raise _BadMessageError("not a JSON object")
    return obj


def _int(o: dict[str, Any], key: str, lo: int, hi: int) -> int:
    v = o.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise _BadMessageError(f"{key}: {str(v)[:40]} is not an integer in [{lo}, {hi}]")
    return v


def _float(v: Any, key: str, bound: float, nullable: bool = False) -> float:
    if v is None and nullable:
        return math.nan
    if not isinstance(v, int | float) or isinstance(v, bool) or not -bound <= v <= bound:
        raise _BadMessageError(f"{key}: {str(v)[:40]} is not a number within +-{bound:g}")
    return float(v)


def _vector(o: dict[str, Any], key: str, n: int, bound: float, nullable: bool = False) -> F64:
    v = o.get(key)
    if not isinstance(v, list) or len(v) != n:
        raise _BadMessageError(f"{key}: not an array of {n} numbers")
    return np.array([_float(x, key, bound, nullable) for x in v], dtype=np.float64)


def _unit_quat(o: dict[str, Any], key: str) -> F64:
    q = _vector(o, key, 4, 2.0)
    if abs(float(np.linalg.norm(q)) - 1.0) > QUAT_NORM_TOLERANCE:
        raise _BadMessageError(f"{key}: not a unit quaternion")
    return q


def _range(o: dict[str, Any]) -> tuple[RangeSample, float]:
    r = RangeSample(
        _int(o, "time_us", 0, MAX_TIME_US),
        _int(o, "sensor_id", 0, 255),
        _float(o.get("distance_m"), "distance_m", MAX_DISTANCE_M),
        _float(o.get("min_m"), "min_m", MAX_DISTANCE_M),
        _float(o.get("max_m"), "max_m", MAX_DISTANCE_M),
        _int(o, "signal_quality", 0, 100),
    )
    if min(r.distance_m, r.min_m) < 0 or r.max_m <= r.min_m:
        raise _BadMessageError("distance_m/min_m/max_m: negative, or max_m not above min_m")
    return r, _float(o.get("true_distance_m"), "true_distance_m", MAX_DISTANCE_M, True)


def _attitude(o: dict[str, Any]) -> AttitudeSample:
    return AttitudeSample(
        _int(o, "time_us", 0, MAX_TIME_US),
        _unit_quat(o, "quat_wxyz"),
        _vector(o, "rates_rad_s", 3, MAX_RATE_RAD_S),
    )


def _imu(o: dict[str, Any]) -> ImuSample:
    accel = _vector(o, "accel_frd_m_s2", 3, MAX_SPECIFIC_FORCE_M_S2)
    if float(np.linalg.norm(accel)) > MAX_SPECIFIC_FORCE_M_S2:
        raise _BadMessageError("accel_frd_m_s2: specific force above 16 g")
    gyro = o.get("gyro_frd_rad_s")
    mag = o.get("mag_frd_gauss")
    return ImuSample(
        _int(o, "time_us", 0, MAX_TIME_US),
        accel,
        None if gyro is None else _vector(o, "gyro_frd_rad_s", 3, MAX_RATE_RAD_S),
        None if mag is None else _vector(o, "mag_frd_gauss", 3, MAX_MAGNETIC_GAUSS),
    )


def _published(o: dict[str, Any]) -> PublishedPose:
    return PublishedPose(
        _int(o, "time_us", 0, MAX_TIME_US),
        _vector(o, "position_ned_m", 3, MAX_POSITION_M),
        _unit_quat(o, "quat_wxyz"),
        _vector(o, "velocity_ned_m_s", 3, MAX_VELOCITY_M_S, nullable=True),
        _int(o, "reset_counter", 0, 255),
        _int(o, "quality_pct", 0, 100),
    )


SAMPLES: dict[str, Any] = {
    ms.RANGE: _range,
    ms.ATTITUDE: _attitude,
    ms.IMU: _imu,
    ms.PUBLISHED: _published,
}


@dataclass
class _Read:
    """What the scan collected: per topic the samples and the frame each was fed before."""

    channels: dict[int, str] = field(default_factory=dict)
    times: list[int] = field(default_factory=list)
    seqs: list[int] = field(default_factory=list)
    held: list[bool] = field(default_factory=list)
    images: list[Where] = field(default_factory=list)
    image: Where | None = None  # the newest image, waiting for its frame record
    samples: dict[str, list[Any]] = field(default_factory=lambda: {t: [] for t in SAMPLES})
    fed: dict[str, list[int]] = field(default_factory=lambda: {t: [] for t in SAMPLES})
    counts: dict[str, RowCount] = field(default_factory=lambda: {t: RowCount() for t in SAMPLES})
    attached: dict[str, bytes] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    def take(self, rec: Record) -> None:
        f = rec.fields
        if rec.kind == "channel" and f["topic"] in ENCODINGS:
            if f["encoding"] != ENCODINGS[f["topic"]]:
                raise TornError(
                    0, f"channel {f['topic']} is {f['encoding']!r}, not {ENCODINGS[f['topic']]}"
                )
            self.channels[f["id"]] = f["topic"]
        elif rec.kind == "attachment" and f["name"] in ATTACHED:
            self.attached[f["name"]] = f["data"]
        elif rec.kind == "metadata":
            self.metadata[f["name"]] = f["data"]
        elif rec.kind == "message" and f["channel_id"] in self.channels and self.ours:
            self._message(self.channels[f["channel_id"]], f["data"], rec.where)

    @property
    def ours(self) -> bool:
        """Our metadata came first: the file is a recording of ours (another's messages on
        topics of the same names are not read)."""
        return self.metadata.get(META_NAME, {}).get("format") == FORMAT_NAME

    def _message(self, topic: str, data: bytes, where: Where | None) -> None:
        at = 0 if where is None else where.chunk
        if topic == ms.IMAGE:
            if len(data) > MAX_IMAGE_BYTES + 1024:
                raise TornError(at, f"an image message of {len(data)} bytes")
            self.image = where
        elif topic == ms.FRAME:
            self._frame(data, at)
        elif topic in SAMPLES:
            try:
                o = _object(data)
                sample = SAMPLES[topic](o)
                k = 0 if topic == ms.PUBLISHED else _int(o, "fed_before_frame", 0, MAX_SEQ)
                fed = self.fed[topic]
                if fed and k < fed[-1]:
                    raise _BadMessageError(f"fed_before_frame: {k} after {fed[-1]} (decreases)")
            except _BadMessageError as e:
                self.counts[topic].add(f"{topic} message {len(self.fed[topic]) + 1}: {e}")
                return
            self.samples[topic].append(sample)
            self.fed[topic].append(k)

    def _frame(self, data: bytes, at: int) -> None:
        n = len(self.times)
        try:
            o = _object(data)
            index, t = _int(o, "index", 0, MAX_SEQ), _int(o, "time_us", 0, MAX_TIME_US)
            seq, held = _int(o, "seq", 0, MAX_SEQ), o.get("held")
            if index != n or (self.times and t <= self.times[-1]) or not isinstance(held, bool):
                raise _BadMessageError(
                    f"index {index}, time_us {t}, held {held!r} out of order or bad"
                )
            if self.image is None:
                raise _BadMessageError("no image before it")
        except _BadMessageError as e:
            raise TornError(at, f"frame record {n}: {e}") from None
        self.times.append(t)
        self.seqs.append(seq)
        self.held.append(held)
        self.images.append(self.image)
        self.image = None


class _Images:
    """The encoded image of a frame by index, read from the file when asked."""

    def __init__(self, path: Path, places: list[Where]) -> None:
        self.path, self.places, self.cache = path, places, dict[int, bytes]()

    def __call__(self, index: int) -> bytes:
        where = f"{self.path} frame {index}"
        try:
            with open_regular(self.path) as fh:
                message = read_at(fh, self.places[index], self.cache)
            data, kind = ms.image_of(message)
        except (TornError, DecodeError, OSError) as e:
            raise DatasetError(f"{where}: the image cannot be read ({e})") from None
        if kind not in ("png", "jpeg"):
            raise DatasetError(f"{where}: image format {kind[:20]!r} (png or jpeg are read)")
        return data


def _meta(strings: dict[str, str]) -> dict[str, Any]:
    """A metadata record's strings as values (true/false, integers)."""
    out: dict[str, Any] = {}
    for k, v in strings.items():
        out[k] = {"true": True, "false": False}.get(
            v, int(v) if v.isascii() and v.isdigit() and len(v) < 19 else v
        )
    return out


def _toml(r: _Read, name: str, path: Path) -> dict[str, Any]:
    raw = r.attached.get(name)
    if raw is None:
        return {}
    if len(raw) > MAX_TOML_BYTES:
        raise DatasetError(f"{path}: attachment {name} larger than {MAX_TOML_BYTES} bytes")
    return parse_toml(
        decode_utf8(raw, f"{path}:{name}", DatasetError), f"{path}:{name}", DatasetError
    )


def read_mcap(path: Path) -> Dataset:
    """The recording in the MCAP file ``path`` (see the module)."""
    with open_regular(path) as fh:
        size = os.fstat(fh.fileno()).st_size
        closed = closed_file(fh, size)
        r = _Read()
        torn = ""
        try:
            for rec in scan(fh, size):
                r.take(rec)
        except TornError as e:
            torn = str(e)
    if torn and closed:
        raise DatasetError(f"{path}: damaged MCAP file: {torn}")
    if META_NAME not in r.metadata:
        why = f" ({torn})" if torn else ""
        raise DatasetError(
            f"{path}: not a {FORMAT_NAME} MCAP recording: no {META_NAME!r} metadata{why}"
        )
    meta = _meta(r.metadata[META_NAME])
    if meta.get("format") != FORMAT_NAME:
        raise DatasetError(
            f"{path}: metadata format {str(meta.get('format'))[:40]!r}, not {FORMAT_NAME}"
        )
    if "calibration.toml" not in r.attached:
        raise DatasetError(f"{path}: no calibration.toml attachment")
    cfg, _ = config_from_tables(
        _toml(r, "calibration.toml", path), _toml(r, "config.toml", path), {}, str(path)
    )
    check_lens(cfg.camera.model(), f"{path}:calibration.toml [camera]")
    end = _meta(r.metadata.get(END_NAME, {}))
    complete = closed and not torn and end.get("complete") is True
    meta.update(end, complete=complete)
    n = len(r.times)
    last_us = r.times[-1] if n else -1
    kept = {
        t: [i for i, k in enumerate(r.fed[t]) if k < n] for t in (ms.RANGE, ms.ATTITUDE, ms.IMU)
    }
    ranges = [r.samples[ms.RANGE][i] for i in kept[ms.RANGE]]
    declared = {s.sensor_id for s in cfg.rangefinders}
    undeclared = sorted({s.sensor_id for s, _ in ranges} - declared)
    if undeclared:
        raise DatasetError(
            f"{path}: ranges of sensor ids {undeclared} that the calibration does not declare"
        )

    def fed(topic: str) -> Any:
        return np.array([r.fed[topic][i] for i in kept[topic]], dtype=np.int64)

    held = np.array(r.held, dtype=bool)
    return Dataset(
        path,
        "companion",
        cfg.camera.model(),
        cfg.camera.T_body_cam(),
        [s.spec() for s in cfg.rangefinders],
        np.array(r.times, dtype=np.int64),
        [],
        [s for s, _ in ranges],
        np.array([t for _, t in ranges], dtype=np.float64),
        [r.samples[ms.ATTITUDE][i] for i in kept[ms.ATTITUDE]],
        config=cfg,
        frame_seqs=np.array(r.seqs, dtype=np.int64),
        fed_before=(fed(ms.RANGE), fed(ms.ATTITUDE)),
        imus=[r.samples[ms.IMU][i] for i in kept[ms.IMU]],
        imu_fed=fed(ms.IMU),
        frame_held=held if held.any() else None,
        frames_checked=meta.get("frames_checked") is True,
        published=[p for p in r.samples[ms.PUBLISHED] if complete or p.time_us <= last_us],
        complete=complete,
        meta=meta,
        skipped={name: c for name, c in r.counts.items() if c.skipped},
        image_bytes=_Images(path, r.images),
    )
