"""``companion eval`` (the VO, every scale method, roll/pitch or d-Pose, on a dataset or a
simulated flight) and ``companion report``: runs from ``companion.offline``, metrics from
``companion.evaluation``, tables and plots from ``companion.reporting``, flights from ``.sim``
(offline and reporting load the Pipeline: imported inside the commands, as in ``bench``).
d-Pose (``--dpose``) is in ``.evaluate_dpose``, the flight phases (``--phases``) in ``.flight``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.cli import sim
from companion.cli.common import (
    EXIT_OK,
    EXIT_USAGE,
    BudgetExceeded,
    add_budget_flags,
    add_sitl_flags,
    load,
    out_dir,
    progress,
    resource_budget,
    run_name,
)
from companion.cli.evaluate_dataset import (
    config_source,
    dataset_config,
    eval_scale_no_world,
    frames_report,
    published_track,
    report_skipped,
    write_honest,
    write_replay,
)
from companion.cli.evaluate_dpose import eval_dpose
from companion.config import STUDY_RANGEFINDERS, Config, triangle_rangefinders
from companion.drivers.dataset import (
    Dataset,
    dataset_steps,
    open_dataset,
    write_poses_csv,
    write_tum,
)
from companion.errors import CompanionError, ConfigError, DatasetError
from companion.evaluation.attitude import SIGMA_STUDY_M, SPACING_STUDY_M, range_tilt_rmse
from companion.vo.focal_check import focal_summary

if TYPE_CHECKING:
    from companion.cli.sim import Flight
    from companion.offline import AttitudeRun


def cmd_eval(args: argparse.Namespace) -> int:
    """Run the pipeline over a dataset and write trajectories (TUM) and metrics, within the
    memory and time budget (--max-memory-mb, --timeout-s). A dataset the reader refuses
    (DatasetError: the message names the file, the row and the field) and a budget exceeded
    are one line on stderr and exit 2, never a traceback."""
    limits = (args.max_memory_mb, args.timeout_s)
    if not all(math.isfinite(v) and v >= 0 for v in limits):
        return _refused("usage", "--max-memory-mb and --timeout-s: finite, >= 0 (0: no limit)")
    try:
        with resource_budget(*limits) as budget:
            try:
                code = _eval(args)
            except BudgetExceeded:
                return _refused("budget exceeded", budget.exceeded)
            except MemoryError:
                return _refused("budget exceeded", "out of memory (--max-memory-mb)")
            except (ImportError, OSError) as e:
                # a library loaded under the memory cap cannot map its code: out of memory too
                if args.max_memory_mb > 0 and _out_of_memory(e):
                    return _refused("budget exceeded", "out of memory (--max-memory-mb)")
                raise
        return _refused("budget exceeded", budget.exceeded) if budget.exceeded else code
    except DatasetError as e:
        return _refused("dataset error", str(e))


def _out_of_memory(e: BaseException) -> bool:
    """Whether an ImportError or OSError is the loader or the OS out of address space."""
    text = str(e).lower()
    return "failed to map segment" in text or "cannot allocate memory" in text


def _refused(kind: str, message: str) -> int:
    """Print one line ``companion: KIND: MESSAGE`` on stderr; return exit 2."""
    print(f"companion: {kind}: {' '.join(message.split())}", file=sys.stderr)
    return EXIT_USAGE


def _eval(args: argparse.Namespace) -> int:
    """The evaluation ``args`` ask for."""
    if args.dataset is not None and (args.phases or args.dpose):
        raise CompanionError("--phases and --dpose run on the simulator, not on a dataset")
    if args.phases:
        from companion.cli.flight import eval_phases

        return eval_phases(args)
    if args.dpose:
        return eval_dpose(args)
    if args.attitude:
        return eval_attitude(args)
    if args.methods == "all":
        return eval_scale(args)
    return eval_vo(args)


# ------------------------------------------------------------------------------ VO
@dataclasses.dataclass
class VoInput:
    """What a VO run reads: a dataset's or a simulated flight's events, and the truth."""

    cfg: Config
    name: str
    total: int
    events: Iterable[Any]
    camera: Any = None  # a dataset's camera model and T_body_cam (None: the config's)
    T_body_cam: Any = None
    gt_at: Callable[[int], Any] | None = None  # true body pose at a time [us], if known
    dataset: Dataset | None = None  # None: a simulated flight
    config_source: str = "the SITL flags"  # where the algorithm options came from


def vo_input(args: argparse.Namespace, name: Callable[[Config], str]) -> VoInput:
    """The dataset folder of ``args.dataset`` or, without one, the simulated flight of the
    SITL flags (named by ``name``)."""
    if args.dataset is not None:
        ds = open_dataset(args.dataset)
        return VoInput(
            dataset_config(ds, args.config),  # its calibration and sensors, none invented
            ds.path.name,
            len(ds),
            ds.events(),  # a recording's: in the order the service fed them
            ds.camera,
            ds.T_body_cam,
            ds.gt_pose_at if ds.has_ground_truth else None,
            ds,
            config_source(ds, args.config),
        )
    cfg = load(args)  # straight from the simulator, no dataset on disk
    flight = sim.scenario(cfg)
    gt_poses: dict[int, Any] = {}
    events = sim.flight_events(flight, gt_poses)
    source = f"{args.config or 'the built-in config'} with the SITL flags"
    return VoInput(
        cfg, name(cfg), flight.n_frames, events, gt_at=gt_poses.__getitem__, config_source=source
    )


def eval_vo(args: argparse.Namespace) -> int:
    """The VO alone: vo.tum, and with ground truth groundtruth.tum, metrics.json, report.md;
    the poses the pipeline gives (poses.tum, poses.csv: exact) and, for a flight recording,
    their difference from the ones the service sent (replay.json)."""
    from companion.offline import run_vo
    from companion.reporting import write_vo_report

    inp = vo_input(args, lambda cfg: run_name(cfg.sitl))
    out = out_dir(args, Path("out") / "eval" / inp.name)
    if inp.dataset is not None:
        report_skipped(inp.dataset, out)
    with progress(inp.total, f"eval {inp.name}", not args.no_progress) as ticks:
        run = run_vo(
            inp.cfg,
            inp.events,
            ticks,
            camera=inp.camera,
            T_body_cam=inp.T_body_cam,
            checked=inp.dataset is not None and inp.dataset.frames_checked,
        )
    times = np.array(run.time_us)
    track = run.tracking_mask()
    T_est = np.array(run.T_vo_cam)
    write_tum(out / "vo.tum", times[track] * 1e-6, T_est[track])
    if run.poses:
        write_poses_csv(out / "poses.csv", run.poses)
        write_tum(out / "poses.tum", *_pose_arrays(run.poses))
    replay = write_replay(inp.dataset, run.poses, out) if inp.dataset is not None else None
    if replay is not None:
        print(replay)
    tracks: dict[str, Any] = {}
    if inp.gt_at is not None and len(times):  # the camera's true trajectory, vs the VO's
        T_body_cam = inp.cfg.camera.T_body_cam() if inp.T_body_cam is None else inp.T_body_cam
        gt = np.array([inp.gt_at(int(t)) @ T_body_cam for t in times])
        write_tum(out / "groundtruth.tum", times * 1e-6, gt)
        print(write_vo_report(run.metrics(gt[:, :3, 3]), out, inp.name))
        if run.poses:  # what the autopilot would get, split at its reset_counter
            tracks["published"] = published_track(run.poses, inp.gt_at)
    frames = frames_report(inp.dataset, inp.total, run.dropped, run.features, run.gaps, run.clock)
    write_honest(out, inp.config_source, frames, tracks, "published")
    if "published" in tracks:
        t = tracks["published"]
        ate = "unavailable" if t.ate_se3_m is None else f"{t.ate_se3_m:.3f} m"
        step = t.largest_reset_step_m
        print(
            f"published: ATE (SE3) {ate}, best constant {t.constant_mean_m:.3f} m, "
            f"{len(t.segments)} segment(s), largest step at a reset "
            + ("none" if step is None else f"{step:.3f} m")
        )
    print(focal_summary(run.lens_focal, run.lens_warning))
    print(f"trajectories and metrics in {out}")
    return EXIT_OK


def _pose_arrays(poses: list[Any]) -> tuple[Any, Any]:
    """Times [s] (N,) and T_world_body (N, 4, 4) of PoseEstimates."""
    from companion.geometry import se3

    times = np.array([p.time_us for p in poses]) * 1e-6
    return times, np.array([se3.from_quat(p.quat_wxyz_ned_frd, p.position_ned_m) for p in poses])


# ------------------------------------------------------------------------------ scale
def eval_scale(args: argparse.Namespace) -> int:
    """Every scale method on one SITL flight or a dataset: tables, TUM trajectories, plots.
    A dataset without a simulated world: metric and Sim(3) ATE only (evaluate_dataset)."""
    from companion.offline import run_scale
    from companion.reporting import write_plots, write_tables, write_trajectories

    source = f"{args.config or 'the built-in config'} with the SITL flags"
    if args.dataset is not None:
        ds = open_dataset(args.dataset)
        if not ds.has_world:
            return eval_scale_no_world(args, ds, args.config)
        source = config_source(ds, args.config)
    study = 6 if args.sensor_study else 0
    cfg, name, world, steps, total = _scale_input(args, study)
    out = out_dir(args, Path("out") / "eval" / name)
    with progress(total, f"eval {name}", not args.no_progress) as ticks:
        run = run_scale(cfg, steps, world, ticks, sensor_study=study)
    table = write_tables(run.metrics(), out, f"Metric scale on {name}")
    frames = frames_report(None, total, run.dropped, gaps=run.gaps, clock=run.clock)
    write_honest(out, source, frames, _tracks(run), cfg.scale.method, run.resets)
    write_trajectories(run, out)
    plots = write_plots(run, world, out)
    print(table)
    print(f"VO resets: {run.resets}")
    print(focal_summary(run.lens_focal, run.lens_warning))
    print(f"tables, TUM trajectories and plots in {out}: " + ", ".join(p.name for p in plots))
    return EXIT_OK


def _tracks(run: Any) -> dict[str, Any]:
    """Every method's whole-flight and segment ATE and its constant baselines (ScaleRun)."""
    from companion.evaluation.methods import method_track

    tracking = np.array(run.tracking, dtype=bool)
    if not tracking.any():
        return {}
    t = np.array(run.time_us) * 1e-6
    gt = np.array(run.gt_position).reshape(-1, 3)
    seg = np.array(run.segment, dtype=np.float64)
    init = float(t[np.argmax(tracking)])
    return {
        n: method_track(t, np.array(run.position[n]).reshape(-1, 3), gt, seg, init)
        for n in run.methods
    }


def _scale_input(args: argparse.Namespace, study: int) -> tuple[Config, str, Any, Any, int]:
    """(config, name, world, steps, frames) of a recorded SITL flight (its world rebuilt from
    meta.toml) or of the simulated flight of the SITL flags."""
    if args.dataset is not None:
        ds = open_dataset(args.dataset)
        if ds.sitl is None or ds.config is None or len(ds.gt_times_us) == 0:
            raise CompanionError(f"{ds.path}: a simulated world needs its ground truth")
        cfg = dataset_config(ds, args.config)  # --config's algorithm options, if given
        if study and len(cfg.rangefinders) < study:
            raise CompanionError("--sensor-study needs a recording with six distance sensors")
        return cfg, ds.path.name, sim.recorded_world(ds), dataset_steps(ds), len(ds)
    cfg = load(args)
    if study and len(cfg.rangefinders) < study:
        cfg = dataclasses.replace(cfg, rangefinders=STUDY_RANGEFINDERS)
    flight = sim.scenario(cfg)
    return cfg, run_name(cfg.sitl), flight.world, flight.steps(), flight.n_frames


# ------------------------------------------------------------------------------ roll/pitch
def eval_attitude(args: argparse.Namespace) -> int:
    """Roll/pitch on one SITL flight: RMSE table, plots and (--study) the spacing and noise
    studies replayed over the same VO run."""
    from companion.offline import run_attitude
    from companion.reporting import write_attitude

    if args.dataset is not None:
        raise CompanionError("--attitude runs on the simulator (the truth is ray cast)")
    cfg = load(args)
    if args.spacing is not None:
        cfg = dataclasses.replace(
            cfg, rangefinders=triangle_rangefinders(args.spacing, args.range_sigma)
        )
    name = run_name(cfg.sitl)
    out = out_dir(args, Path("out") / "eval" / f"{name}-attitude")
    flight = sim.scenario(cfg)
    with progress(flight.n_frames, f"attitude {name}", not args.no_progress) as ticks:
        run = run_attitude(cfg, flight.steps(), ticks, keep_frames=args.study)
    table = write_attitude(run, out, f"Roll/pitch on {name}")
    ms = np.array([m for m in run.attitude_ms if m > 0])
    print(table)
    if len(ms):
        print(f"roll/pitch cost: median {np.median(ms):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms")
    if args.study:
        _attitude_study(args, cfg, flight, run, out, name)
    print(f"tables and plots in {out}")
    return EXIT_OK


def _attitude_study(
    args: argparse.Namespace, cfg: Config, flight: Flight, run: AttitudeRun, out: Path, name: str
) -> None:
    """The range tilts' RMSE against sensor spacing and range noise, replayed over the VO
    views of ``run`` with simulated sensors on a triangle."""
    from companion.offline import replay_attitude
    from companion.reporting import write_attitude_study

    frame_us = [f[0] for f in run.frames]
    settle = (np.array(frame_us) - run.time_us[0]) * 1e-6 >= 5.0
    truth = run.array("truth")[np.isin(run.time_us, frame_us)]

    def point(spacing_m: float, sigma_m: float) -> dict[str, float]:
        rfs = triangle_rangefinders(spacing_m, sigma_m)
        ranges = sim.range_simulator(flight, rfs, cfg.sitl.seed)
        specs = {rf.sensor_id: rf.spec() for rf in rfs}
        # the published (fused) attitude does not use the ranges by default: the study is
        # about the range tilts themselves
        series = replay_attitude(run, specs, cfg.attitude, ranges.valid_at)
        return range_tilt_rmse(series, truth, settle, sigma_m, spacing_m)

    sigma0 = args.range_sigma
    spacing0 = args.spacing or 0.5
    study = {
        "spacing": [(L, point(L, sigma0)) for L in SPACING_STUDY_M],
        "sigma": [(sg, point(spacing0, sg)) for sg in SIGMA_STUDY_M],
    }
    text, png_path = write_attitude_study(study, out, f"Roll/pitch studies on {name}")
    (out / "attitude_study.md").write_text(text + "\n")
    print(text)
    print(f"study plot: {png_path}")


# ------------------------------------------------------------------------------ report
def cmd_report(args: argparse.Namespace) -> int:
    """Summarise `eval --methods all` folders (TERRAIN-TRAJECTORY-SEED) in Markdown; with
    ``--rows``, one line per flight NAME over its NAME-SEED folders."""
    from companion.reporting import summary
    from companion.reporting.rows import read_rows, rows_table

    if args.sim_vs_real:
        return _sim_vs_real([str(d) for d in args.dirs], args.plot)
    if args.rows:
        rows = read_rows([Path(d) for d in args.dirs])
        if not rows:
            raise CompanionError("no NAME-SEED folder of a simulated flight's evaluation")
        print(rows_table(rows))
        return EXIT_OK
    text = summary([Path(d) for d in args.dirs])
    if not text:
        raise CompanionError(
            "no TERRAIN-TRAJECTORY-SEED folders or real-sequence folders with scale_metrics.json"
        )
    print(text)
    return EXIT_OK


def _sim_vs_real(pairs: list[str], plot: Path | None) -> int:
    """``companion report --sim-vs-real REAL=SIM ...``: each real sequence's folder beside its
    simulated look-alike's SIM-SEED folders."""
    from companion.reporting.sim_vs_real import (
        comparison_plot,
        comparison_table,
        real_errors,
        seed_folders,
        sim_errors,
    )

    rows = []
    for pair in pairs:
        real, sep, sim = pair.partition("=")
        sims = seed_folders(Path(sim))
        if not sep or not sims:
            raise ConfigError(f"{pair}: REAL_FOLDER=SIM_PREFIX, with SIM_PREFIX-SEED folders")
        try:
            errors = (sim_errors(sims), real_errors(Path(real)))
        except (ValueError, OSError, KeyError) as e:
            raise ConfigError(f"{pair}: {e}") from None
        rows.append((f"{Path(real).name} / {Path(sim).name}", *errors))
    print(comparison_table(rows))
    if plot is not None:
        print(f"plot: {comparison_plot(rows, plot)}")
    return EXIT_OK


# ------------------------------------------------------------------------------ parsers
def add_report(sub: Any) -> None:
    """``companion report``."""
    p_rep = sub.add_parser("report", help="summarise scale evaluations over seeds")
    p_rep.add_argument(
        "dirs", nargs="+", type=Path, help="`eval --methods all` folders (TERRAIN-TRAJECTORY-SEED)"
    )
    p_rep.add_argument(
        "--rows",
        action="store_true",
        help="one line per flight over its seeds, folders named NAME-SEED (the published "
        "method's ATE by seed, VO resets, the baselines)",
    )
    p_rep.add_argument(
        "--sim-vs-real",
        action="store_true",
        help="the folders are REAL=SIM pairs: a real sequence's evaluation beside its "
        "simulated look-alike's SIM-SEED folders (docs/RESULTS.md)",
    )
    p_rep.add_argument("--plot", type=Path, help="with --sim-vs-real: a PNG of the pairs")
    p_rep.set_defaults(func=cmd_report)


def add_eval(sub: Any) -> None:
    """``companion eval``."""
    p = sub.add_parser("eval", help="evaluate the pipeline on a dataset or a SITL flight")
    p.add_argument("dataset", type=Path, nargs="?", help="dataset folder (default: SITL)")
    add_sitl_flags(p)
    p.add_argument("--out", type=Path, help="output folder (default out/eval/NAME)")
    p.add_argument(
        "--methods",
        choices=["vo", "all"],
        default="vo",
        help="vo: the odometry alone; all: every scale method (SITL)",
    )
    p.add_argument(
        "--sensor-study", action="store_true", help="with --methods all: M-MSC with 1..6 sensors"
    )
    p.add_argument(
        "--attitude", action="store_true", help="roll/pitch from the distance sensors (SITL)"
    )
    p.add_argument(
        "--spacing", type=float, help="--attitude: 3 sensors on a triangle of this side [m]"
    )
    p.add_argument(
        "--range-sigma", type=float, default=0.01, help="--attitude: range noise sigma [m]"
    )
    p.add_argument(
        "--study", action="store_true", help="--attitude: RMSE vs sensor spacing and range noise"
    )
    p.add_argument(
        "--dpose", action="store_true", help="d-Pose over painted laser marks (SITL, spiral)"
    )
    p.add_argument(
        "--random", type=int, default=0, help="--dpose: N random synthetic poses instead"
    )
    p.add_argument(
        "--phases", action="store_true", help="published poses by flight phase (SITL; issue 18)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_budget_flags(p)
    p.set_defaults(func=cmd_eval)
