"""``companion replay``: last week's flight recordings through this version of the pipeline.

Each recording (our dataset format, read through ``companion.drivers.dataset.open_dataset``
only) is fed to a fresh ``Pipeline`` in the order the service fed it (``run_vo``, as
``companion eval`` does), with the calibration and the algorithm options it flew with
(``Dataset.config``: its calibration.toml and config.toml), or with an override file laid
over those options key by key (:func:`read_override`, :func:`replay_config`). Out comes one
flat table of metrics per recording (:func:`replay_recording`): the frames and the poses, the
tracked fraction, the VO's resets, the pipeline's CPU per frame, the replayed poses against
the ones the service sent (``published.csv``) and, where the recording has ground truth,
their ATE (``companion.evaluation.segments.track_accuracy``, the same figure ``companion
eval`` prints for the published track). :func:`replay_document` gathers the recordings with
what ran them (the software's version and commit, the override's SHA-256, the date);
``companion.replay_compare`` compares two such documents.

Units: times [ms] of CPU (``time.process_time``, with OpenCV on one thread: one core's work;
reading the images is not counted), positions [m], angles [deg].
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import subprocess
import time
import typing
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from companion import __version__
from companion.bounded import read_regular_file
from companion.config import Config, from_dict, to_dict
from companion.drivers.dataset import Dataset, PublishedPose, open_dataset
from companion.drivers.dataset.format import ALGORITHM_SECTIONS
from companion.errors import CompanionError, ConfigError, DatasetError
from companion.geometry import so3
from companion.offline import VoRun, run_vo
from companion.pipeline import Event, Pipeline
from companion.toml_files import MAX_CONFIG_BYTES, decode_utf8, merge, parse_toml
from companion.types import CameraFrame, PoseEstimate, VoState

REPLAY_FORMAT = "companion-replay"
REPLAY_VERSION = 1
_SECTION_TYPES: dict[str, type[Any]] = {
    name: hint for name, hint in typing.get_type_hints(Config).items() if name in ALGORITHM_SECTIONS
}

Progress = Callable[[int, str], AbstractContextManager[Iterator[None] | None]]


@dataclass(frozen=True, slots=True)
class Override:
    """An override file as read: its path, the SHA-256 of its bytes, and its tables
    ({section: {key: value}}, sections among ``ALGORITHM_SECTIONS``)."""

    path: Path
    sha256: str
    tables: dict[str, dict[str, Any]]


def read_override(path: Path) -> Override:
    """The override file ``path``: a TOML with [vo] [scale] [attitude] [dpose] tables only.

    Every key is checked on its own against its section (an unknown key, a bad type or a
    value out of bounds is a ConfigError naming it, before any recording is opened). Any
    other table ([camera], [[rangefinders]], [service], ...) is refused by name: a replay
    keeps each recording's calibration and sensors, what its images and ranges were taken
    with."""
    raw = read_regular_file(Path(path), MAX_CONFIG_BYTES, ConfigError)  # errors name it
    data = parse_toml(decode_utf8(raw, str(path)), str(path))
    tables: dict[str, dict[str, Any]] = {}
    for key, table in data.items():
        if key not in ALGORITHM_SECTIONS:
            raise ConfigError(
                f"{path}: {key}: a replay keeps each recording's calibration and sensors; "
                f"an override holds only {', '.join(f'[{s}]' for s in ALGORITHM_SECTIONS)}"
            )
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: {key}: expected a table, got {table!r}")
        try:
            from_dict(_SECTION_TYPES[key], table, f"{key}.")
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from None
        tables[key] = table
    return Override(Path(path), hashlib.sha256(raw).hexdigest(), tables)


def replay_config(own: Config | None, override: Override | None) -> Config:
    """The config a recording replays with: its own (``Dataset.config``: the calibration and
    the algorithm options it flew with; a dataset without one: the built-in options and no
    sensors), each key of ``override`` replacing the recording's value of that key (the
    other keys of a section stay the recording's). ConfigError naming the key when the
    merged options do not fit the recording (an ``attitude.sensor_ids`` naming a sensor it
    lacks)."""
    base = own
    if base is None:
        base = dataclasses.replace(
            Config(),
            rangefinders=(),
            attitude=dataclasses.replace(Config().attitude, sensor_ids=()),
        )
    if override is None or not override.tables:
        return base
    sections = {}
    for name, table in override.tables.items():
        merged = merge(to_dict(getattr(base, name)), table)  # tables inside merged too
        sections[name] = from_dict(_SECTION_TYPES[name], merged, f"{name}.")
    try:
        return dataclasses.replace(base, **sections)
    except ConfigError as e:
        raise ConfigError(f"{override.path}: {e}") from None


def recording_id(ds: Dataset) -> str:
    """A recording's identity, wherever its folder now lies: the SHA-256 of its frame times
    (int64, little-endian; a monotonic clock in microseconds does not repeat across
    flights), 16 hex digits."""
    times = np.ascontiguousarray(ds.frame_times_us, dtype="<i8")
    return hashlib.sha256(times.tobytes()).hexdigest()[:16]


class _CpuPerFrame:
    """The process's CPU time [ms] of each frame's work in ``run_vo``: from the moment the
    frame leaves :meth:`events` (read and decoded) to ``observe`` (its pose and keyframe work
    done). A frame the pipeline raised on has no figure."""

    def __init__(self) -> None:
        self._start = 0.0
        self.ms: list[float] = []

    def events(self, events: Iterable[Event]) -> Iterator[Event]:
        for ev in events:
            if isinstance(ev, CameraFrame):
                self._start = time.process_time()
            yield ev

    def observe(self, frame: CameraFrame, pipe: Pipeline) -> None:
        self.ms.append((time.process_time() - self._start) * 1e3)


def spread_ms(prefix: str, ms: Sequence[float]) -> dict[str, float | None]:
    """``{prefix}_median``, ``_p95``, ``_p99``, ``_max``, ``_mean`` of ``ms`` (None if empty)."""
    a = np.asarray(ms, dtype=np.float64)
    if not len(a):
        return {f"{prefix}_{k}": None for k in ("median", "p95", "p99", "max", "mean")}
    return {
        f"{prefix}_median": float(np.median(a)),
        f"{prefix}_p95": float(np.percentile(a, 95)),
        f"{prefix}_p99": float(np.percentile(a, 99)),
        f"{prefix}_max": float(a.max()),
        f"{prefix}_mean": float(a.mean()),
    }


def _yaw_rad(quat_wxyz: Any) -> float:
    return so3.matrix_to_rpy(so3.quat_to_matrix(quat_wxyz))[2]


def _angle_deg(q_a: Any, q_b: Any) -> float:
    """The rotation angle [deg] between two unit quaternions (q and -q the same) from their
    chord, |q_a - q_b| = 2 sin(angle / 4): exactly 0 for equal ones (an arccos of their dot
    product is not, by a few 1e-6 deg)."""
    a, b = np.asarray(q_a, dtype=np.float64), np.asarray(q_b, dtype=np.float64)
    if float(np.dot(a, b)) < 0.0:
        b = -b
    half_chord = min(1.0, float(np.linalg.norm(a - b)) / 2.0)
    return float(np.degrees(4.0 * np.arcsin(half_chord)))


def _same_bits(a: Any, b: Any) -> bool:
    """Equal, value for value (NaN equals NaN: unknown on both sides)."""
    return bool(np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True))


def against_published(
    published: Sequence[PublishedPose], poses: Sequence[PoseEstimate]
) -> dict[str, Any]:
    """The replayed poses against the ones the service sent, matched by frame time: counts,
    the position difference [m] (largest and 95th percentile), the yaw and the whole
    rotation's difference [deg], the largest velocity difference [m/s] over the components
    known on both sides and how many poses have a velocity known on one side only (NaN: not
    yet known), and ``identical``: every published pose replayed with the
    same bits (position, quaternion, velocity). reset_counter is not compared: the wire's
    continues across the service's restarts."""
    by_time = {p.time_us: p for p in poses}
    pos: list[float] = []
    yaw: list[float] = []
    ang: list[float] = []
    vel: list[float] = []
    velocity_one_sided = 0
    identical = bool(published)
    for sent in published:
        mine = by_time.get(sent.time_us)
        if mine is None:
            identical = False
            continue
        pos.append(float(np.linalg.norm(mine.position_ned_m - sent.position_ned_m)))
        dyaw = _yaw_rad(mine.quat_wxyz_ned_frd) - _yaw_rad(sent.quat_wxyz)
        yaw.append(abs(float(np.degrees(np.angle(np.exp(1j * dyaw))))))
        ang.append(_angle_deg(mine.quat_wxyz_ned_frd, sent.quat_wxyz))
        known = np.isnan(mine.velocity_ned_m_s) == np.isnan(sent.velocity_ned_m_s)
        if not known.all():  # known on one side only
            velocity_one_sided += 1
        dv = np.abs(mine.velocity_ned_m_s - sent.velocity_ned_m_s)
        vel.append(float(np.nan_to_num(dv, nan=0.0).max()))
        identical = identical and all(
            _same_bits(x, y)
            for x, y in (
                (mine.position_ned_m, sent.position_ned_m),
                (mine.quat_wxyz_ned_frd, sent.quat_wxyz),
                (mine.velocity_ned_m_s, sent.velocity_ned_m_s),
            )
        )
    sent_times = {p.time_us for p in published}

    def top(values: list[float], q: float | None = None) -> float | None:
        if not values:
            return None
        return float(max(values) if q is None else np.percentile(values, q))

    return {
        "published_poses": len(published),
        "published_matched": len(pos),
        "published_missing": len(published) - len(pos),
        "replayed_not_published": sum(p.time_us not in sent_times for p in poses),
        "position_diff_max_m": top(pos),
        "position_diff_p95_m": top(pos, 95),
        "yaw_diff_max_deg": top(yaw),
        "yaw_diff_p95_deg": top(yaw, 95),
        "angle_diff_max_deg": top(ang),
        "velocity_diff_max_m_s": top(vel),
        "velocity_known_one_side": velocity_one_sided,
        "identical": identical,
    }


def against_truth(ds: Dataset, poses: Sequence[PoseEstimate]) -> dict[str, float | None]:
    """The replayed poses against the recording's ground truth (their positions NED against
    the true body positions at their times, split at their reset_counter): the whole-flight
    SE(3) ATE [m] and as % of the true path, and the ATE over the best constant's
    (``companion.evaluation.segments``; 1 = no better than standing still)."""
    from companion.evaluation.segments import track_accuracy
    from companion.evaluation.trajectory import path_length

    t_s = np.array([p.time_us for p in poses], dtype=np.float64) * 1e-6
    est = np.array([p.position_ned_m for p in poses], dtype=np.float64).reshape(-1, 3)
    gt = np.array([ds.gt_pose_at(p.time_us)[:3, 3] for p in poses]).reshape(-1, 3)
    track = track_accuracy(t_s, est, gt, [p.reset_counter for p in poses])
    path_m = path_length(gt) if len(gt) > 1 else 0.0
    ate = track.ate_se3_m
    return {
        "ate_m": ate,
        "ate_pct_path": None if ate is None or path_m <= 0 else 100.0 * ate / path_m,
        "ate_to_best_constant": track.ratio_to_mean,
        "path_m": path_m,
    }


class Beside(Protocol):
    """Work run beside the replay on every frame, after its CPU time is read (a benchmark's
    floor: the CLI's KLT floor, ``companion.bench_vo.KltFloor``): ``start`` with the config
    the recording replays with, called with each frame after its work, then ``metrics`` with
    the run and the CPU [ms] of each of its frames (``run.time_us``'s; more flat metrics)."""

    def start(self, config: Config) -> None: ...

    def __call__(self, frame: CameraFrame, pipe: Pipeline) -> None: ...

    def metrics(self, run: VoRun, cpu_ms: Sequence[float]) -> dict[str, Any]: ...


def replay_recording(
    path: Path,
    override: Override | None = None,
    progress: Progress | None = None,
    beside: Beside | None = None,
) -> dict[str, Any]:
    """Replay one recording (its own config, or ``override`` laid over it) and measure it:
    ``{"path", "name", "id", "software", "complete", "config", "metrics"}``, ``metrics``
    flat (numbers, flags, None where the recording cannot say). OpenCV runs on one thread
    (as ``companion bench vo``): the CPU per frame is one core's work, steadier from run to
    run (the poses are the same bits). Raises what opening or reading the recording raises
    (DatasetError naming the file and the row) and ConfigError when the override does not
    fit it."""
    import cv2

    ds = open_dataset(path)
    cfg = replay_config(ds.config, override)
    cpu = _CpuPerFrame()
    if beside is not None:
        beside.start(cfg)

    def observe(frame: CameraFrame, pipe: Pipeline) -> None:
        cpu.observe(frame, pipe)
        if beside is not None:
            beside(frame, pipe)

    label = f"replay {ds.path.name}"
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with progress(len(ds), label) if progress is not None else nullcontext(None) as ticks:
            run = run_vo(
                cfg,
                cpu.events(ds.events()),
                ticks,
                camera=ds.camera,
                T_body_cam=ds.T_body_cam,
                checked=ds.frames_checked,
                observe=observe,
            )
    finally:
        cv2.setNumThreads(threads)
    counters = [p.reset_counter for p in run.poses]
    tracked = sum(s == VoState.TRACKING for s in run.state)
    metrics: dict[str, Any] = {
        "frames": len(ds),
        "frames_replayed": len(run.time_us),
        "poses": len(run.poses),
        "tracked_fraction": tracked / len(ds) if len(ds) else None,
        "vo_resets": run.resets,
        "reset_counter_steps": int(np.count_nonzero(np.diff(counters))) if counters else 0,
        "pipeline_errors": run.errors,
        **spread_ms("cpu_ms", cpu.ms),
        "wall_ms_median": float(np.median(run.total_ms)) if run.total_ms else None,
    }
    if beside is not None:
        metrics.update(beside.metrics(run, cpu.ms))
    if ds.published:
        metrics.update(against_published(ds.published, run.poses))
    if ds.has_ground_truth and len(run.poses) >= 3:
        metrics.update(against_truth(ds, run.poses))
    software = ds.meta.get("software")
    return {
        "path": str(path),
        "name": ds.path.name,
        "id": recording_id(ds),
        "software": software if isinstance(software, str) and software else None,
        "complete": ds.complete,
        "config": "its own" if override is None else f"its own with {override.path}",
        "metrics": metrics,
    }


def replay_failed(path: Path, error: BaseException) -> dict[str, Any]:
    """The entry of a recording that could not be opened or replayed: its error, one line."""
    if isinstance(error, ConfigError):
        kind = "config error"
    elif isinstance(error, DatasetError):
        kind = "dataset error"
    elif isinstance(error, CompanionError):
        kind = "error"
    else:  # a crash mid-replay: its type says what broke
        kind = f"crash ({type(error).__name__})"
    message = " ".join(str(error).split()) or type(error).__name__
    return {"path": str(path), "name": Path(path).name, "error": message, "kind": kind}


def software_commit() -> dict[str, Any]:
    """The git commit of the code that runs (the package's checkout) and whether files
    differ from it; None for both outside a git checkout."""
    here = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": head or None, "dirty": bool(dirty)}


def finite_or_none(value: Any) -> Any:
    """``value`` with every float that is not finite replaced by None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [finite_or_none(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def replay_document(recordings: list[dict[str, Any]], override: Override | None) -> dict[str, Any]:
    """The replay file: what ran (version, commit), the override (its path and SHA-256,
    None: each recording's own options), when (UTC), and the recordings' entries."""
    return {
        "format": REPLAY_FORMAT,
        "version": REPLAY_VERSION,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "software": {"version": __version__, **software_commit()},
        "override": None
        if override is None
        else {"path": str(override.path), "sha256": override.sha256, "tables": override.tables},
        "recordings": finite_or_none(recordings),
        "failed": sum("error" in r for r in recordings),
    }
