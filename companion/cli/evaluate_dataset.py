"""``companion eval DIR`` on datasets that are not a simulated flight: the config a dataset runs
with (its own calibration and declared sensors, nothing invented), the replay check of a
flight recording (``companion run --record``), and the scale methods side by side on a dataset
without a simulated world (``--methods all``). Nothing here reaches the simulator: a dataset
that declares no world is evaluated without one (tests/companion/evaluation/test_evaluation.py
checks that ``sitl`` is never imported).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from companion.cli.common import EXIT_OK, out_dir, progress
from companion.config import Config, load_config, to_dict
from companion.drivers.dataset import Dataset, PublishedPose, dataset_steps, write_tum
from companion.drivers.dataset.format import ALGORITHM_SECTIONS
from companion.errors import CompanionError, ConfigError
from companion.evaluation.tables import markdown_table
from companion.geometry import so3
from companion.toml_files import read_config_toml
from companion.types import PoseEstimate
from companion.vo.focal_check import focal_summary

NO_RANGES = "the dataset has no distance sensors (ranges.csv): no metric scale"


def dataset_config(ds: Dataset, config_path: Path | None) -> Config:
    """The config a dataset runs with (docs/dataset.md, "Which config a dataset runs with").

    The camera, T_body_cam and the distance sensors are always the dataset's own (its
    calibration; EuRoC's sensor.yaml, no sensors). The algorithm options ([vo] [scale]
    [attitude] [dpose]) are ``--config FILE``'s (the file over the built-in defaults, as
    ``companion run --config FILE`` would fly them), else a recording's own config.toml, else
    the built-in ones. The whole file is validated: an unknown key or a bad value is a
    ConfigError naming it (exit 2); a [camera] or [[rangefinders]] in the file that differs
    from the dataset's is a warning naming the keys (the dataset's calibration wins);
    [service], [record] and [sitl] do not apply to a replay and are not used."""
    if config_path is None:
        if ds.config is not None:
            return ds.config
        return _without_sensors(Config())
    cfg = load_config(config_path)
    for line in calibration_conflicts(ds, read_config_toml(Path(config_path)), cfg):
        print(f"companion: warning: {config_path}: {line}", file=sys.stderr)
    if ds.config is None:
        return _without_sensors(cfg)
    try:
        return dataclasses.replace(ds.config, **{k: getattr(cfg, k) for k in ALGORITHM_SECTIONS})
    except ConfigError as e:  # e.g. attitude.sensor_ids naming a sensor the dataset lacks
        raise ConfigError(f"{config_path} on {ds.path.name}: {e}") from None


def _without_sensors(cfg: Config) -> Config:
    """``cfg`` with no distance sensors (a dataset that declares none has none)."""
    return dataclasses.replace(
        cfg, rangefinders=(), attitude=dataclasses.replace(cfg.attitude, sensor_ids=())
    )


def config_source(ds: Dataset, config_path: Path | None) -> str:
    """Where a dataset's algorithm options came from (for the report)."""
    if config_path is not None:
        return str(config_path)
    if ds.config is not None and ds.folder is not None and ds.folder.exists("config.toml"):
        return "the recording's config.toml"
    if ds.config is not None and ds.path.suffix == ".mcap":
        return "the recording's config.toml (attached to the MCAP file)"
    return "the built-in defaults"


def _flat(table: Any, prefix: str) -> dict[str, Any]:
    """A nested table as {dotted key: leaf value}."""
    if not isinstance(table, dict):
        return {prefix: table}
    out: dict[str, Any] = {}
    for k, v in table.items():
        out.update(_flat(v, f"{prefix}.{k}"))
    return out


def calibration_conflicts(ds: Dataset, raw: dict[str, Any], cfg: Config) -> list[str]:
    """What a config file's [camera] and [[rangefinders]] (``raw``: the file as read, ``cfg``:
    as validated) say that the dataset's calibration does not: one line per table, naming the
    keys that differ (the dataset's calibration is used)."""
    lines: list[str] = []
    own = ds.config
    if "camera" in raw:
        given = _flat(to_dict(cfg.camera), "camera")
        theirs = _flat(to_dict(own.camera), "camera") if own is not None else {}
        keys = sorted(set(_flat(raw["camera"], "camera")) & set(given))
        differ = [k for k in keys if own is None or given[k] != theirs.get(k)]
        if differ:
            lines.append(
                f"{', '.join(differ[:6])}{' ...' if len(differ) > 6 else ''} "
                f"{'differs' if len(differ) == 1 else 'differ'} from the dataset's own "
                "calibration: the dataset's is used"
            )
    if "rangefinders" in raw:
        ours = own.rangefinders if own is not None else ()
        if cfg.rangefinders != ours:
            lines.append(
                f"rangefinders (ids {[r.sensor_id for r in cfg.rangefinders]}) differ from "
                f"the sensors the dataset declares (ids {[r.sensor_id for r in ours]}): "
                "the dataset's are used"
            )
    return lines


def report_skipped(ds: Dataset, out: Path) -> None:
    """The rows the reader left out (a word or NaN in a number, a zero quaternion, a short
    row): one warning per file on stderr and their counts in ``out/skipped_rows.json``
    (nothing when none was)."""
    if not ds.skipped:
        return
    for line in ds.skipped_text():
        print(f"companion: warning: {line}", file=sys.stderr)
    counts = {name: {"skipped": c.skipped, "first": c.first} for name, c in ds.skipped.items()}
    (out / "skipped_rows.json").write_text(json.dumps(counts, indent=2) + "\n")


def frames_report(
    ds: Dataset | None,
    frames: int,
    dropped: dict[str, int],
    features: Sequence[int] = (),
    gaps: int = 0,
    clock: Any = None,
) -> dict[str, Any]:
    """The frames not given to the VO (``dropped``: by reason, companion.evaluation.frames;
    plus a recording's frames the service held): one line on stderr when any were, and the
    figures for the report (frames, given to the VO, by reason, the line, and the median of
    the features tracked per frame given to the VO, ``features``, when known; ``gaps``: new
    VO maps after more than vo.max_gap_ms without a usable frame; ``clock``: the camera
    clock's ClockReport, a line on stderr when frames were re-timed)."""
    from companion.evaluation.frames import dropped_line, dropped_total

    counts = {k: int(v) for k, v in dropped.items() if v}
    if ds is not None and ds.frame_held is not None and ds.frame_held.any():
        counts["held_by_service"] = int(ds.frame_held.sum())
    line = dropped_line(frames, counts)
    if line is not None:
        print(line, file=sys.stderr)
    given = frames - dropped_total(counts)
    median = float(np.median(features)) if len(features) else None
    jitter = None
    if clock is not None and clock.retimed:
        from companion.vo.frame_clock import jitter_warning

        jitter = f"eval: {jitter_warning(clock)}"
        print(jitter, file=sys.stderr)
    return {
        "clock": jitter,
        "frames": frames,
        "given_to_vo": given,
        "not_given_to_vo": counts,
        "line": line,
        "features_median": median,
        "gaps": gaps,
    }


def frames_markdown(frames: dict[str, Any]) -> list[str]:
    """The report's lines on the frames not given to the VO."""
    lines = [
        "## Frames not given to the VO",
        "",
        frames["line"] or f"all {frames['frames']} frames were given to the VO",
    ]
    if frames.get("gaps"):
        lines.append(
            f"{frames['gaps']} time(s) no usable frame for longer than vo.max_gap_ms: "
            "the VO started a new map"
        )
    if frames.get("clock"):
        lines.append(frames["clock"].removeprefix("eval: "))
    if frames.get("features_median") is not None:
        lines.append(f"(features tracked per frame: median {frames['features_median']:g})")
    return lines


def track_json(track: Any) -> dict[str, Any]:
    """A TrackAccuracy as JSON (its segments and reset steps as lists of objects)."""
    doc = {k: getattr(track, k) for k in track.__slots__}
    doc["segments"] = [dataclasses.asdict(s) for s in track.segments]
    doc["reset_steps"] = [dataclasses.asdict(s) for s in track.reset_steps]
    doc["largest_reset_step_m"] = track.largest_reset_step_m
    return doc


def tracks_markdown(tracks: dict[str, Any], detail: str | None) -> list[str]:
    """The report's table of whole-flight ATE against the constant-position baselines, one row
    per track, and the per-segment table of the track ``detail``."""
    lines = [
        "## Whole flight, segments and a constant position",
        "",
        "ATE after an SE(3) alignment against two constants: the start held (no alignment) "
        "and the best constant (the mean true position: what any constant scores aligned). "
        "A ratio of 1 is no better than standing still. The published poses: every one; a "
        "scale method: from 5 s after the VO's first pose, as the metric ATE above.",
        "",
    ]
    rows = [
        [
            name,
            str(t.frames),
            _fmt(t.ate_se3_m, " m", 3),
            _fmt(t.constant_start_m, " m", 3),
            _fmt(t.constant_mean_m, " m", 3),
            _fmt(t.ratio_to_mean, "", 3),
            str(len(t.segments)),
            "no reset" if t.largest_reset_step_m is None else f"{t.largest_reset_step_m:.3f} m",
        ]
        for name, t in tracks.items()
    ]
    header = ["track", "frames", "ATE (SE3)", "start held", "best constant"]
    header += ["ATE / best constant", "segments", "largest step at a reset"]
    lines.append(markdown_table(header, rows))
    chosen = tracks.get(detail) if detail is not None else None
    if chosen is not None and chosen.segments:
        seg_rows = [
            [
                str(g.segment),
                str(g.frames),
                f"{g.duration_s:.1f} s",
                _fmt(g.ate_se3_m, " m", 3),
                _fmt(g.constant_mean_m, " m", 3),
            ]
            for g in chosen.segments
        ]
        lines += ["", f"Segments of {detail} (each aligned on its own):", ""]
        lines.append(
            markdown_table(
                ["segment", "frames", "duration", "ATE (SE3)", "best constant"], seg_rows
            )
        )
        lines += [""] if chosen.reset_steps else []
        for r in chosen.reset_steps:
            lines.append(
                f"- reset at {r.time_s:.2f} s: the track steps {r.step_m:.3f} m, "
                f"the truth {r.true_step_m:.3f} m"
            )
    return lines


def write_honest(
    out: Path,
    config: str,
    frames: dict[str, Any],
    tracks: dict[str, Any],
    detail: str | None,
    vo_resets: int | None = None,
) -> None:
    """eval.json (where the algorithm options came from, the frames not given to the VO, by
    track the whole-flight and segment ATE against a constant position, and the VO's resets
    when given) and the same as sections at the end of report.md (after the evaluation's own
    report, if any)."""
    doc: dict[str, Any] = {
        "config": config,
        "frames": frames,
        "tracks": {n: track_json(t) for n, t in tracks.items()},
    }
    if vo_resets is not None:
        doc["vo_resets"] = vo_resets
    (out / "eval.json").write_text(json.dumps(doc, indent=2) + "\n")
    lines = [f"Algorithm options from {config}.", "", *frames_markdown(frames)]
    if tracks:
        lines += ["", *tracks_markdown(tracks, detail)]
    report = out / "report.md"
    before = report.read_text() if report.exists() else ""
    report.write_text(before + ("\n" if before else "") + "\n".join(lines) + "\n")


def published_track(poses: Sequence[PoseEstimate], gt_at: Any) -> Any:
    """The published poses (their positions NED, split at their reset_counter) against the
    true body positions at their times (``gt_at(time_us)``: T_world_body (4, 4))."""
    from companion.evaluation.segments import track_accuracy

    t = np.array([p.time_us for p in poses], dtype=np.float64) * 1e-6
    est = np.array([p.position_ned_m for p in poses]).reshape(-1, 3)
    gt = np.array([gt_at(p.time_us)[:3, 3] for p in poses]).reshape(-1, 3)
    return track_accuracy(t, est, gt, [p.reset_counter for p in poses])


def _max_diff(a: np.ndarray, b: np.ndarray) -> float:
    """Largest |a - b|; NaN against NaN (unknown on both sides) agrees, NaN against a number
    does not (inf)."""
    both = np.isnan(a) & np.isnan(b)
    d = np.where(both, 0.0, np.abs(a - b))
    return float(np.nan_to_num(d, nan=np.inf).max())


def _quat_angle_rad(q_a: np.ndarray, q_b: np.ndarray) -> float:
    """The rotation angle between two unit quaternions (wxyz; q and -q are the same)."""
    return float(2.0 * np.arccos(min(1.0, abs(float(np.dot(q_a, q_b))))))


def replay_check(
    published: Sequence[PublishedPose], poses: Sequence[PoseEstimate]
) -> dict[str, Any]:
    """The replayed poses against the ones the service sent, matched by frame time: how many
    match, and the largest position [m], orientation [rad] and velocity [m/s] differences.
    (reset_counter is not compared: the service sends a counter that continues across its
    restarts, the replay starts at 0.)"""
    by_time = {p.time_us: p for p in poses}
    pos, ang, vel = [0.0], [0.0], [0.0]
    missing = 0
    for sent in published:
        mine = by_time.get(sent.time_us)
        if mine is None:
            missing += 1
            continue
        pos.append(_max_diff(mine.position_ned_m, sent.position_ned_m))
        ang.append(_quat_angle_rad(mine.quat_wxyz_ned_frd, sent.quat_wxyz))
        vel.append(_max_diff(mine.velocity_ned_m_s, sent.velocity_ned_m_s))
    return {
        "published": len(published),
        "replayed": len(poses),
        "matched": len(published) - missing,
        "missing": missing,
        "max_position_diff_m": max(pos),
        "max_angle_diff_rad": max(ang),
        "max_velocity_diff_m_s": max(vel),
    }


def write_replay(ds: Dataset, poses: Sequence[PoseEstimate], out: Path) -> str | None:
    """A recording's replay against its published.csv: replay.json; returns the line to
    print (None when the dataset has no published poses)."""
    if not ds.published:
        return None
    check = replay_check(ds.published, poses)
    (out / "replay.json").write_text(json.dumps(check, indent=2) + "\n")
    return (
        f"replay vs the flight: {check['matched']} of {check['published']} published poses "
        f"replayed, max |dposition| {check['max_position_diff_m']:.3g} m, max angle "
        f"{check['max_angle_diff_rad']:.3g} rad"
        + (
            " (the recording did not close: read to its last complete frame)"
            if not ds.complete
            else ""
        )
    )


# ------------------------------------------------------------------------------ no world
def eval_scale_no_world(args: argparse.Namespace, ds: Dataset, config_path: Path | None) -> int:
    """Every scale method on a dataset without a simulated world: metric (SE3) and Sim(3) ATE
    against its ground truth side by side, per segment and against a constant position; the
    frames not given to the VO; the figures that need a true scale unavailable."""
    from companion.evaluation.methods import MethodAccuracy, method_track, trajectory_accuracy
    from companion.evaluation.vo import vo_metrics
    from companion.offline import run_scale

    cfg = dataset_config(ds, config_path)
    study = 6 if args.sensor_study else 0
    if study and len(cfg.rangefinders) < study:
        raise CompanionError("--sensor-study needs a recording with six distance sensors")
    name = ds.path.name
    out = out_dir(args, Path("out") / "eval" / name)
    report_skipped(ds, out)
    with progress(len(ds), f"eval {name}", not args.no_progress) as ticks:
        run = run_scale(
            cfg,
            dataset_steps(ds),
            None,
            ticks,
            sensor_study=study,
            camera=ds.camera,
            T_body_cam=ds.T_body_cam,
        )
    t = np.array(run.time_us) * 1e-6
    tracking = np.array(run.tracking, dtype=bool)
    gt = np.array(run.gt_position).reshape(-1, 3)
    segment = np.array(run.segment, dtype=np.float64)
    missing = NO_RANGES if not ds.ranges else ""
    rows: list[MethodAccuracy] = []
    tracks: dict[str, Any] = {}
    if tracking.any():
        init = float(t[np.argmax(tracking)])
        R = so3.rot_z(run.yaw_vo_rad)
        for n in run.methods:
            pos = np.array(run.position[n]).reshape(-1, 3)
            rows.append(trajectory_accuracy(n, t, pos, gt, R, init, missing=missing))
            if ds.has_ground_truth:
                tracks[n] = method_track(t, pos, gt, segment, init)
    vo = None
    if tracking.any() and ds.has_ground_truth:
        vo = vo_metrics(
            run.time_us,
            tracking,
            run.segment,
            run.resets,
            np.array(run.vo_position).reshape(-1, 3),
            np.array(run.gt_cam_position).reshape(-1, 3),
        )
    extra = {
        "config": config_source(ds, config_path),
        "frames": frames_report(ds, len(ds), run.dropped, gaps=run.gaps, clock=run.clock),
        "tracks": tracks,
        "published_method": cfg.scale.method,
    }
    table = _write_no_world(rows, vo, run, ds, out, extra)
    print(table)
    print(f"VO resets: {run.resets}")
    print(focal_summary(run.lens_focal, run.lens_warning))
    print(f"tables and TUM trajectories in {out}")
    return EXIT_OK


def _fmt(v: float | None, unit: str, digits: int) -> str:
    return "unavailable" if v is None else f"{v:.{digits}f}{unit}"


def _write_no_world(
    rows: list[Any], vo: Any, run: Any, ds: Dataset, out: Path, extra: dict[str, Any]
) -> str:
    """scale_metrics.json, report.md and the TUM trajectories of a no-world evaluation;
    ``extra``: the config's source, the frames report, the tracks by method."""
    tracks = extra["tracks"]
    doc = {
        "dataset": str(ds.path),
        "world": None,
        "ground_truth": ds.has_ground_truth,
        "distance_sensors": [r.sensor_id for r in ds.rangefinders],
        "config": extra["config"],
        "frames": extra["frames"],
        "methods": [dataclasses.asdict(r) for r in rows],
        "tracks": {n: track_json(t) for n, t in tracks.items()},
        "vo": None if vo is None else {k: getattr(vo, k) for k in vo.__slots__},
    }
    (out / "scale_metrics.json").write_text(json.dumps(doc, indent=2) + "\n")
    header = ["method", "frames", "metric ATE (SE3)", "ATE % path", "Sim(3) ATE"]
    header += ["Sim(3) scale", "final error", "scale MSE"]
    metrics = markdown_table(
        header,
        (
            [
                r.method,
                str(r.frames),
                _fmt(r.ate_se3_m, " m", 3),
                _fmt(r.ate_se3_pct, " %", 2),
                _fmt(r.ate_sim3_m, " m", 3),
                _fmt(r.sim3_scale, "", 4),
                _fmt(r.final_error_m, " m", 2),
                _fmt(r.scale_mse, "", 2),
            ]
            for r in rows
        ),
    )
    reasons = sorted({why for r in rows for why in r.unavailable.values()})
    notes = [f"- unavailable: {why}" for why in reasons]
    if vo is not None:
        notes.append(
            f"- raw VO (unscaled), longest segment ({vo.segment_frames} frames): Sim(3) ATE "
            f"{vo.ate_sim3_m:.3f} m ({vo.ate_sim3_pct:.2f} % of {vo.path_m:.1f} m)"
        )
    if not rows:
        notes.append("- the VO never tracked: no method has an estimate")
    notes.append(f"- algorithm options from {extra['config']}")
    more = frames_markdown(extra["frames"])
    if tracks:
        more += ["", *tracks_markdown(tracks, extra["published_method"])]
    table = "\n".join([metrics, "", *notes, "", *more])
    (out / "report.md").write_text(f"# Metric scale on {ds.path.name} (no world)\n\n{table}\n")
    from companion.evaluation.trajectory import poses_from_positions

    t = np.array(run.time_us) * 1e-6
    if ds.has_ground_truth:
        gt = np.array(run.gt_position).reshape(-1, 3)
        write_tum(out / "groundtruth.tum", t, poses_from_positions(gt))
    for n in run.methods:
        p = np.array(run.position[n]).reshape(-1, 3)
        ok = np.all(np.isfinite(p), axis=1)
        name = n.replace(" ", "_").replace("=", "")
        write_tum(out / f"{name}.tum", t[ok], poses_from_positions(p[ok]))
    return table
