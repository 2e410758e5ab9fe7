"""Import the RIS lab's downward flight (github ris-lab/opticflow-direct) into our format.

The only public real sequence we found that looks at the ground from above with metric
ground truth: a small flying robot over a floor tiled with checkerboard sheets, a grey
320 x 240 camera at a nominal 60 Hz (``images60fps/test<N>.png``), and a motion-capture
record at 500 Hz (``mocap_data.mat``, struct ``mocap`` with ``time`` [s], ``frame`` (the image
index that was newest when the sample was taken), ``X Y Z`` [m], ``qx qy qz`` (``qw``
omitted: recovered as ``sqrt(1 - |q|^2)``)). Paper: Chirarattananon, Bioinspir. Biomim.
13(3), 2018. The repository states no licence: convert it locally, never commit it.

What the source gives and what this importer makes of it:

- **Frame stamps**: a frame's stamp is the time of the first motion-capture sample tagged with
  it, minus the camera-to-capture latency ``LATENCY_S`` (26 ms, measured below; the source's
  ``flow_comparison.m`` uses 42 samples, 84 ms, which put the truth 3-4 frames early). These
  stamps jitter as a real driver's do (intervals of 2 ms to 130 ms around the camera's
  16.6 ms) and are written as they are: the service must cope. Frames no sample was tagged
  with have no stamp, and frames exposed before the record began have no truth: both are
  left out (counted).
- **Ground truth** is taken at each frame's *exposure* time: the stamps' local line over the
  frame index (least squares over the neighbouring +-``GT_HALF_WINDOW`` frames, refitted on
  the earlier half of them: deliveries are late, never early), so the truth does not
  inherit the stamps' jitter.
- **Frames**: the capture's world is z-up and its quaternion turns the world into the body
  (``R_capturebody_captureworld``), but in a world turned 90 deg about z from the one of its
  positions (``R_CAPTUREWORLD_ATTITUDEWORLD``); the camera looks down the body's -z with its
  image axes along the body's -x and +y (``R_CAPTUREBODY_CAM``). Measured, not taken from the
  source (2026-12-01, docs/decisions.md "rislab's truth, reconciled with its images"): for
  pairs of frames 3 apart, KLT tracks of the floor against where the truth's two poses put
  the same floor points. Every axis order of the camera in the body with the positions and
  attitudes in one world (384 readings) left 8.3 px of a 11.0 px flow unexplained (the
  earlier reading included); attitudes turned 90 deg about z from the positions, 1.3 px at
  the best focal (a simulated look-alike, whose conventions are known: 2.7 of 10.5 px).
  The earlier reading (camera axes +x and -y of the body, one world) came from the VO's own
  relative rotations correlating with the truth's by 0.73 / 0.56 / 0.96 about the camera's
  x / y / z: the yaw alone was right. Written here as our conventions: world z down (the
  capture's world turned 180 deg about x), body FRD, the camera mounted like the built-in
  one (``rpy_deg = [0, 0, 90]``) at the body's origin.
- **Distance sensors** are *synthesised* from the ground truth and the floor (the plane
  ``z = FLOOR_Z_M`` of the capture's world, from the source's ``Z - 0.013``): the configured
  ``[[rangefinders]]`` (their mounts, limits and noise model), sampled at their ``rate_hz``,
  with seeded noise. They test what the metric scale does with real images, not a real
  sensor's faults; meta.toml says so (``rangefinders_source``).
- **Attitude**: the sequence has no autopilot; ``attitude.csv`` is made from the ground
  truth at 100 Hz with 0.1 deg of noise, as the simulator's autopilot sends it, so the
  pipeline gets what it would get in flight (the gravity priors, the north of its frame, the
  focal check). meta.toml says so (``attitude_source``).
- **Camera**: no calibration ships (the source's code implies 235.5 or 471 px). The lens is
  an argument (``focal_px``, ``dist``), written into calibration.toml; config/
  real_sequences.toml gives the one fitted to the floor's flow against the truth.
"""

from __future__ import annotations

import csv
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from companion.config import Config, MountConfig, RangefinderConfig
from companion.drivers.dataset.format import (
    ATTITUDE_COLUMNS,
    FORMAT_NAME,
    FORMAT_VERSION,
    RANGE_COLUMNS,
)
from companion.drivers.dataset.import_write import ImportSummary
from companion.drivers.dataset.toml_text import toml_dumps
from companion.drivers.dataset.tum import write_tum
from companion.drivers.dataset.writer import calibration_tables
from companion.errors import DatasetError
from companion.geometry import se3, so3
from companion.types import F64

LATENCY_S = 0.026  # camera -> capture latency (measured: the module's docstring, "Frames")
FLOOR_Z_M = 0.013  # the floor in the capture's world (flow_comparison.m: Z - 0.013)
GT_HALF_WINDOW = 30  # frames either side of the local line that times the exposures
WIDTH, HEIGHT = 320, 240
# the camera's axes in the capture's body: x = -x_body, y = y_body, z = -z_body (measured)
R_CAPTUREBODY_CAM = np.diag([-1.0, 1.0, -1.0])
R_WORLD_CAPTUREWORLD = np.diag([1.0, -1.0, -1.0])  # z up -> z down
# the attitudes' world is the positions' turned -90 deg about z (measured: the docstring)
R_CAPTUREWORLD_ATTITUDEWORLD = so3.rot_z(np.radians(-90.0))


def _beam(
    sensor_id: int, x_m: float, y_m: float, roll_deg: float, pitch_deg: float
) -> RangefinderConfig:
    return RangefinderConfig(
        sensor_id=sensor_id,
        mount=MountConfig(xyz_m=(x_m, y_m, 0.0), rpy_deg=(roll_deg, pitch_deg, 0.0)),
        min_m=0.05,
        max_m=12.0,
        sigma_a_m=0.01,
    )


# four sensors on a small quadrotor's arms, 5 cm from the camera, a few degrees off vertical
RISLAB_BEAMS: tuple[RangefinderConfig, ...] = (
    _beam(0, 0.05, 0.02, -1.5, 3.7),
    _beam(1, -0.016, 0.054, -3.8, -1.1),
    _beam(2, -0.048, -0.024, 1.8, -3.6),
    _beam(3, 0.024, -0.04, 3.0, 1.8),
)


@dataclass(frozen=True, slots=True)
class Capture:
    """The motion-capture record: time (S,) [s], frame (S,) image index, position (S, 3) [m]
    and R_capturebody_captureworld (S, 3, 3), the record's quaternion as a matrix (it turns
    the world into the body: see the module's docstring); the all-zero rows removed."""

    time_s: F64
    frame: np.ndarray
    position_m: F64
    R_capturebody_captureworld: F64


def read_capture(path: Path) -> Capture:
    """``mocap_data.mat`` as a Capture; DatasetError naming the file for anything else."""
    import scipy.io

    try:
        mat = scipy.io.loadmat(str(path), squeeze_me=True, struct_as_record=False)
        mc = mat["mocap"]
        cols = {f: np.asarray(getattr(mc, f), dtype=np.float64) for f in mc._fieldnames}
    except (OSError, ValueError, KeyError, AttributeError, TypeError) as exc:
        raise DatasetError(f"{path}: not the capture record (struct mocap): {exc}") from exc
    missing = {"time", "frame", "X", "Y", "Z", "qx", "qy", "qz"} - set(cols)
    if missing:
        raise DatasetError(f"{path}: struct mocap lacks {sorted(missing)}")
    # an all-zero row is no sample (the source's first); frame 0 = before the camera's first
    ok = np.any([cols[c] != 0 for c in ("X", "Y", "Z", "qx", "qy", "qz")], axis=0)
    q_xyz = np.column_stack([cols["qx"], cols["qy"], cols["qz"]])[ok]
    norm2 = np.sum(q_xyz**2, axis=1)
    if not np.all(np.isfinite(q_xyz)) or np.any(norm2 > 1.0 + 1e-3):
        raise DatasetError(f"{path}: qx qy qz are not the vector part of unit quaternions")
    q_wxyz = np.column_stack([np.sqrt(np.clip(1.0 - norm2, 0.0, 1.0)), q_xyz])
    R = np.stack([so3.quat_to_matrix(q / np.linalg.norm(q)) for q in q_wxyz])
    position = np.column_stack([cols["X"], cols["Y"], cols["Z"]])[ok]
    return Capture(cols["time"][ok], cols["frame"][ok].astype(np.int64), position, R)


def exposure_times(frame: np.ndarray, stamp_s: F64, half: int = GT_HALF_WINDOW) -> F64:
    """(F,) exposure times [s] of frames (F,) with jittery stamps (F,): each frame's value on
    a line over the frame index fitted to its neighbours' stamps (+-``half`` frames), refitted
    twice on the earlier half of them (residual at most the median): a delivery is late,
    never early, so the early stamps carry the camera's clock plus its constant latency."""
    out = np.empty(len(frame))
    for i in range(len(frame)):
        lo, hi = max(0, i - half), min(len(frame), i + half + 1)
        f, t = frame[lo:hi].astype(np.float64) - frame[i], stamp_s[lo:hi]
        keep = np.ones(len(f), dtype=bool)
        coef = np.array([t.mean(), 0.0])
        for _ in range(3):
            if keep.sum() < 3:
                break
            A = np.column_stack([np.ones(keep.sum()), f[keep]])
            coef, *_ = np.linalg.lstsq(A, t[keep], rcond=None)
            resid = t - (coef[0] + coef[1] * f)
            keep = resid <= np.median(resid)
        out[i] = coef[0]
    return out


def body_poses(capture: Capture, times_s: F64) -> F64:
    """(N, 4, 4) T_world_body in our conventions at ``times_s`` (N,) [s]: the nearest capture
    sample (2 ms apart), its world turned z-down and its body turned into FRD with the camera
    mounted as the built-in one (rpy 0, 0, 90 deg: camera x = body y)."""
    idx = np.clip(np.searchsorted(capture.time_s, times_s), 1, len(capture.time_s) - 1)
    before = capture.time_s[idx - 1]
    idx = np.where(times_s - before < capture.time_s[idx] - times_s, idx - 1, idx)
    R_cam_body = so3.rot_z(np.radians(90.0)).T
    R_cb_body = R_CAPTUREBODY_CAM @ R_cam_body
    poses = np.empty((len(times_s), 4, 4))
    for n, i in enumerate(idx):
        R_cw_cb = R_CAPTUREWORLD_ATTITUDEWORLD @ capture.R_capturebody_captureworld[i].T
        R = R_WORLD_CAPTUREWORLD @ R_cw_cb @ R_cb_body
        poses[n] = se3.make(R, R_WORLD_CAPTUREWORLD @ capture.position_m[i])
    return poses


def beam_range_m(T_world_body: F64, T_body_rf: F64, floor_z_m: float) -> float | None:
    """Distance [m] along a sensor's beam (+z of its frame) to the floor ``z = floor_z_m``
    of our z-down world, None when the beam does not point at it."""
    T = T_world_body @ T_body_rf
    origin, beam = T[:3, 3], T[:3, 2]
    if beam[2] <= 1e-6:
        return None
    return float((floor_z_m - origin[2]) / beam[2])


def import_rislab(
    src: Path,
    out: Path,
    config: Config,
    rangefinders: tuple[RangefinderConfig, ...] = RISLAB_BEAMS,
    *,
    focal_px: float,
    dist: tuple[float, float, float, float, float],
    frames: tuple[int, int] | None = None,
    seed: int = 0,
) -> ImportSummary:
    """Write the sequence in ``src`` (images60fps/, mocap_data.mat) to the empty folder
    ``out`` in our format: ``config``'s camera section with this lens (``focal_px``, ``dist``),
    and ``rangefinders`` synthesised over the floor; ``frames`` (A, B): only image indexes
    A <= i < B."""
    capture = read_capture(src / "mocap_data.mat")
    ids, first = np.unique(capture.frame, return_index=True)
    stamps = capture.time_s[first] - LATENCY_S
    keep = ids > 0
    if frames is not None:
        keep &= (ids >= frames[0]) & (ids < frames[1])
    ids, stamps = ids[keep], stamps[keep]
    exposure = exposure_times(ids, stamps)
    # frames exposed before the record began have no truth: left out with the untagged
    covered = (exposure >= capture.time_s[0]) & (exposure <= capture.time_s[-1])
    ids, stamps, exposure = ids[covered], stamps[covered], exposure[covered]
    if len(ids) < 2:
        raise DatasetError(f"{src}: fewer than two tagged frames with truth in the range asked")
    span = int(ids[-1] - ids[0] + 1)
    camera = replace(
        config.camera,
        width=WIDTH,
        height=HEIGHT,
        fx=focal_px,
        fy=focal_px,
        cx=(WIDTH - 1) / 2,
        cy=(HEIGHT - 1) / 2,
        dist=dist,
        rate_hz=60.0,
        mount=replace(config.camera.mount, xyz_m=(0.0, 0.0, 0.0), rpy_deg=(0.0, 0.0, 90.0)),
    )
    cfg = replace(config, camera=camera, rangefinders=rangefinders)
    if out.exists() and any(out.iterdir()):
        raise DatasetError(f"{out} exists and is not empty")
    (out / "images").mkdir(parents=True, exist_ok=True)
    t0 = float(min(stamps[0], exposure[0]))  # the dataset's time 0

    def us(t: float) -> int:
        return int(round((t - t0) * 1e6))

    with (out / "frames.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_us", "seq", "filename"])
        for i, t in zip(ids, stamps, strict=True):
            name = f"images/{int(i):06d}.png"
            source = src / "images60fps" / f"test{int(i)}.png"
            if not source.is_file():
                raise DatasetError(f"{source}: image missing")
            shutil.copyfile(source, out / name)
            w.writerow([us(float(t)), int(i), name])
    poses = body_poses(capture, exposure)
    write_tum(out / "groundtruth.txt", np.array([us(float(t)) for t in exposure]) * 1e-6, poses)
    n_ranges = _write_ranges(out, capture, cfg.rangefinders, exposure, t0, seed)
    _write_attitude(out, capture, exposure, t0, seed)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    path_m = float(steps.sum())
    tables = calibration_tables(cfg)
    (out / "calibration.toml").write_text(toml_dumps(tables))
    meta = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "frames": len(ids),
        "path_length_m": path_m,
        "world": "none",
        "source": "ris-lab/opticflow-direct (images60fps, mocap_data.mat)",
        "licence": "none stated (all rights reserved): local evaluation only",
        "attitude_source": (
            "synthesised from the ground truth at 100 Hz with 0.1 deg of noise (an autopilot's "
            "estimate stands in; the sequence has no autopilot)"
        ),
        "rangefinders_source": (
            "synthesised from the ground truth over a flat floor (not a real sensor's readings)"
        ),
        "stamps": (
            "first capture sample tagged with the frame minus 26 ms (as delivered: jittery); "
            "ground truth at the stamps' local line (the exposure)"
        ),
        "frames_without_stamp": span - len(ids),
    }
    (out / "meta.toml").write_text(toml_dumps(meta))
    return ImportSummary(
        len(ids), n_ranges, path_m, {"frames without a stamp or truth": span - len(ids)}
    )


ATTITUDE_RATE_HZ = 100.0
ATTITUDE_SIGMA_DEG = 0.1


def _write_attitude(out: Path, capture: Capture, exposure: F64, t0: float, seed: int) -> None:
    """attitude.csv: R_world_body at 100 Hz over the frames' span (times [s] less ``t0``)
    with 0.1 deg of white noise (as the simulator's autopilot), and the body rates from
    successive true attitudes [rad/s, FRD]: what an autopilot would send, made from the
    ground truth (the sequence flew none of ours)."""
    rng = np.random.default_rng(seed + 1)
    dt_s = 1.0 / ATTITUDE_RATE_HZ
    times = np.arange(exposure[0], exposure[-1] + dt_s, dt_s)
    poses = body_poses(capture, np.append(times, times[-1] + dt_s))
    with (out / "attitude.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(ATTITUDE_COLUMNS)
        for i, t in enumerate(times):
            R, R_next = poses[i, :3, :3], poses[i + 1, :3, :3]
            rate = so3.log(R.T @ R_next) / dt_s
            noise = so3.exp(rng.normal(0.0, np.radians(ATTITUDE_SIGMA_DEG), 3))
            q = so3.matrix_to_quat(R @ noise)
            w.writerow(
                [int(round((float(t) - t0) * 1e6)), *(f"{v:.9f}" for v in q)]
                + [f"{v:.6f}" for v in rate]
            )


def _write_ranges(
    out: Path,
    capture: Capture,
    sensors: tuple[RangefinderConfig, ...],
    exposure: F64,
    t0: float,
    seed: int,
) -> int:
    """ranges.csv: every sensor at its rate over the frames' span (times [s] less ``t0``),
    the floor distance along its beam plus seeded noise (sigma = a + b * range), clipped to
    its limits (then signal_quality 1)."""
    rng = np.random.default_rng(seed)
    floor_z = float((R_WORLD_CAPTUREWORLD @ np.array([0.0, 0.0, FLOOR_Z_M]))[2])
    rows: list[tuple[int, int, float, float, float, int, float]] = []
    for s in sensors:
        times = np.arange(exposure[0], exposure[-1], 1.0 / s.rate_hz)
        T_body_rf = s.mount.T_body_sensor()
        for t, T_world_body in zip(times, body_poses(capture, times), strict=True):
            true_m = beam_range_m(T_world_body, T_body_rf, floor_z)
            if true_m is None:
                continue
            reading = true_m + rng.normal(0.0, s.sigma_a_m + s.sigma_b * true_m)
            quality = 100
            if not s.min_m <= true_m <= s.max_m:
                reading, quality = float(np.clip(true_m, s.min_m, s.max_m)), 1
            time_us = int(round((float(t) - t0) * 1e6))
            rows.append((time_us, s.sensor_id, reading, s.min_m, s.max_m, quality, true_m))
    rows.sort()
    with (out / "ranges.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([*RANGE_COLUMNS, "true_distance_m"])
        for r in rows:
            w.writerow([r[0], r[1], f"{r[2]:.4f}", r[3], r[4], r[5], f"{r[6]:.4f}"])
    return len(rows)
