"""Command line: ``companion sitl record|sheet``, ``companion config``, ``companion bench``.

Exit codes: 0 success, 1 a runtime error (message on stderr), 2 a bad configuration or bad
arguments (the message names the key), 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from companion import __version__
from companion.config import Config, describe, load_config
from companion.errors import CompanionError, ConfigError

EXIT_OK, EXIT_ERROR, EXIT_CONFIG, EXIT_INTERRUPTED = 0, 1, 2, 130


def _sitl_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """CLI flags -> nested config overrides (only the flags the user gave)."""
    sitl: dict[str, Any] = {}
    for flag, key in (
        ("terrain", "terrain"),
        ("trajectory", "trajectory"),
        ("seed", "seed"),
        ("seconds", "seconds"),
        ("altitude", "altitude_m"),
        ("speed", "speed_m_s"),
    ):
        value = getattr(args, flag, None)
        if value is not None:
            sitl[key] = value
    if getattr(args, "takeoff_landing", False):
        sitl["takeoff_landing"] = True
    if getattr(args, "laser_marks", None) is not None:
        sitl["render"] = {"laser_marks": args.laser_marks}
    return {"sitl": sitl} if sitl else {}


def _load(args: argparse.Namespace) -> Config:
    return load_config(getattr(args, "config", None), _sitl_overrides(args))


def cmd_config(args: argparse.Namespace) -> int:
    """Print every option with its value and help, after the checks `run` makes before it
    starts (files, URLs, the status socket path): a file that passes here starts there."""
    from companion.service import preflight

    cfg = _load(args)
    warnings = preflight.check(cfg)
    print("\n".join(describe(cfg)))
    for text in warnings:
        print(f"companion: warning: {text}", file=sys.stderr)
    return EXIT_OK


def cmd_sitl_record(args: argparse.Namespace) -> int:
    """Record a SITL dataset."""
    from sitl.dataset import record

    cfg = _load(args)
    out = record(
        cfg,
        args.out,
        image_format=args.image_format,
        overwrite=args.overwrite,
        progress=not args.no_progress,
    )
    print(out)
    return EXIT_OK


def cmd_sitl_sheet(args: argparse.Namespace) -> int:
    """Write a PNG contact sheet of a dataset and print its path."""
    from drivers.dataset import open_dataset
    from sitl.dataset import contact_sheet

    path = contact_sheet(open_dataset(args.dataset), args.out)
    print(path)
    return EXIT_OK


def cmd_bench_render(args: argparse.Namespace) -> int:
    """Benchmark SITL rendering (frames/s on one core)."""
    from companion.bench import bench_render, format_render_report

    cfg = _load(args)
    report = bench_render(cfg, args.terrains, args.frames)
    print(format_render_report(report))
    return EXIT_OK


def _progress(total: int, desc: str, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(
        total=total,
        unit="frame",
        desc=desc,
        file=sys.stderr,
        disable=not enabled,
        dynamic_ncols=True,
    )


def _ticks(bar: Any) -> Iterator[None]:
    while True:
        bar.update(1)
        yield None


def cmd_eval_scale(args: argparse.Namespace) -> int:
    """Every scale method on one SITL flight: tables, TUM trajectories and plots."""
    from dataclasses import replace

    import numpy as np

    from companion.config import STUDY_RANGEFINDERS
    from companion.offline import run_scale
    from companion.reporting import run_metrics, write_plots, write_tables
    from drivers.dataset import write_tum
    from sitl.scenario import Scenario

    study = 6 if args.sensor_study else 0
    steps: Any
    if args.dataset is not None:  # a recorded SITL flight: its world is rebuilt from meta.toml
        from drivers.dataset import dataset_steps, open_dataset
        from sitl.world import make_world

        ds = open_dataset(args.dataset)
        if ds.sitl is None or ds.config is None or len(ds.gt_times_us) == 0:
            raise CompanionError(
                f"{ds.path}: --methods all needs a simulated recording (the ground-truth "
                "scale ray casts its world)"
            )
        if study and len(ds.config.rangefinders) < study:
            raise CompanionError("--sensor-study needs a recording with six distance sensors")
        cfg = ds.config
        name = ds.path.name
        world = make_world(
            ds.sitl.terrain, ds.sitl.seed, ds.sitl.world_size_m, ds.sitl.height_resolution_m
        )
        steps, total = dataset_steps(ds), len(ds)
    else:
        cfg = _load(args)
        if study and len(cfg.rangefinders) < study:
            cfg = replace(cfg, rangefinders=STUDY_RANGEFINDERS)
        s = cfg.sitl
        name = f"sitl-{s.terrain}-{s.trajectory}-{s.seconds:g}s-seed{s.seed}"
        scenario = Scenario(cfg)
        world, steps, total = scenario.world, scenario.steps(), scenario.n_frames
    out = Path(args.out) if args.out else Path("out") / "eval" / name
    out.mkdir(parents=True, exist_ok=True)
    bar = _progress(total, f"eval {name}", not args.no_progress)
    run = run_scale(cfg, steps, world, _ticks(bar), sensor_study=study)
    bar.close()
    metrics = run_metrics(run)
    table = write_tables(metrics, out, f"Metric scale on {name}")
    t = np.array(run.time_us) * 1e-6
    eye = np.eye(4)
    write_tum(
        out / "groundtruth.tum",
        t,
        np.array([np.block([[eye[:3, :3], p[:, None]], [eye[3:]]]) for p in run.gt_position]),
    )
    for n in run.methods:
        p = np.array(run.position[n])
        ok = np.all(np.isfinite(p), axis=1)
        poses = np.repeat(eye[None], int(ok.sum()), axis=0)
        poses[:, :3, 3] = p[ok]
        write_tum(out / f"{n.replace(' ', '_').replace('=', '')}.tum", t[ok], poses)
    plots = write_plots(run, world, out)
    print(table)
    print(f"VO resets: {run.resets}")
    print(f"tables, TUM trajectories and plots in {out}: " + ", ".join(p.name for p in plots))
    return EXIT_OK


def cmd_report(args: argparse.Namespace) -> int:
    """Summarise `eval --methods all` folders (TERRAIN-TRAJECTORY-SEED) in Markdown."""
    from companion.reporting import summary

    text = summary([Path(d) for d in args.dirs])
    if not text:
        raise CompanionError("no TERRAIN-TRAJECTORY-SEED folders with scale_metrics.json")
    print(text)
    return EXIT_OK


def cmd_eval_attitude(args: argparse.Namespace) -> int:
    """Roll/pitch on one SITL flight: RMSE table, plots and (--study) the spacing and noise
    studies replayed over the same VO run."""
    import dataclasses

    import numpy as np

    from companion.config import triangle_rangefinders
    from companion.evaluation.attitude import angle_errors, single_sample_bound_deg
    from companion.offline import replay_attitude, run_attitude
    from companion.reporting import write_attitude, write_attitude_study
    from sitl.scenario import Scenario
    from sitl.sensors import RangeSimulator

    if args.dataset is not None:
        raise CompanionError("--attitude runs on the simulator (the truth is ray cast)")
    cfg = _load(args)
    if args.spacing is not None:
        rfs = triangle_rangefinders(args.spacing, args.range_sigma)
        cfg = dataclasses.replace(cfg, rangefinders=rfs)
    s = cfg.sitl
    name = f"sitl-{s.terrain}-{s.trajectory}-{s.seconds:g}s-seed{s.seed}"
    out = Path(args.out) if args.out else Path("out") / "eval" / f"{name}-attitude"
    out.mkdir(parents=True, exist_ok=True)
    scenario = Scenario(cfg)
    bar = _progress(scenario.n_frames, f"attitude {name}", not args.no_progress)
    run = run_attitude(cfg, scenario.steps(), _ticks(bar), keep_frames=args.study)
    bar.close()
    table = write_attitude(run, out, f"Roll/pitch on {name}")
    ms = np.array([m for m in run.attitude_ms if m > 0])
    print(table)
    if len(ms):
        print(f"roll/pitch cost: median {np.median(ms):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms")
    if args.study:
        truth = run.array("truth")
        t = (np.array([f[0] for f in run.frames]) - run.time_us[0]) * 1e-6
        settle = t >= 5.0
        truth_f = truth[np.isin(run.time_us, [f[0] for f in run.frames])]

        def point(spacing_m: float, sigma_m: float) -> dict[str, float]:
            rfs = triangle_rangefinders(spacing_m, sigma_m)
            sim = RangeSimulator(scenario.world, scenario.trajectory, rfs, s.seed)
            specs = {rf.sensor_id: rf.spec() for rf in rfs}
            series = replay_attitude(run, specs, cfg.attitude, sim.valid_at)
            # the published (fused) attitude does not use the ranges by default: the study is
            # about the range tilts themselves
            vals = {
                n: angle_errors(series[n], truth_f, settle).rmse_deg for n in ("ground", "gravity")
            }
            vals["bound"] = single_sample_bound_deg(sigma_m, spacing_m)
            return vals

        sigma0 = args.range_sigma
        spacing0 = args.spacing or 0.5
        study = {
            "spacing": [(L, point(L, sigma0)) for L in np.round(np.arange(0.1, 1.01, 0.1), 2)],
            "sigma": [(sg, point(spacing0, sg)) for sg in (0.0, 0.005, 0.01, 0.02, 0.05, 0.1)],
        }
        text, png_path = write_attitude_study(study, out, f"Roll/pitch studies on {name}")
        (out / "attitude_study.md").write_text(text + "\n")
        print(text)
        print(f"study plot: {png_path}")
    print(f"tables and plots in {out}")
    return EXIT_OK


DPOSE_ARM_S = 1.0  # d-Pose runs: the marks are painted (and d-Pose armed) at this time [s]


def _dpose_config(args: argparse.Namespace) -> Config:
    """The SITL config of a d-Pose run: the four d-Pose lasers, marks painted at DPOSE_ARM_S,
    the spiral flight unless another trajectory is asked for."""
    import dataclasses

    from companion.config import dpose_rangefinders

    overrides = _sitl_overrides(args)
    overrides.setdefault("sitl", {}).setdefault("trajectory", "spiral")
    cfg = load_config(getattr(args, "config", None), overrides)
    render = dataclasses.replace(cfg.sitl.render, laser_marks="painted", painted_time_s=DPOSE_ARM_S)
    return dataclasses.replace(
        cfg,
        rangefinders=dpose_rangefinders(),
        sitl=dataclasses.replace(cfg.sitl, render=render),
    )


def cmd_eval_dpose(args: argparse.Namespace) -> int:
    """d-Pose on a SITL flight over its painted marks (spiral, 2-8 m, yaw over the full circle)
    against the VO, or (--random N) over N random synthetic poses."""
    import numpy as np

    cfg = _dpose_config(args)
    if args.random:
        from companion.dpose.solve import reference_points
        from companion.evaluation.dpose import random_pose_study

        T = np.stack([r.spec().T_body_rf for r in cfg.rangefinders])
        o, u = T[:, :3, 3], T[:, :3, 2]
        pattern = reference_points(o, u, (3.0 - o[:, 2]) / u[:, 2])  # armed 3 m over level ground
        for distractors in (0, 2):
            st = random_pose_study(
                cfg.camera.model(),
                cfg.camera.T_body_cam(),
                pattern,
                args.random,
                seed=cfg.sitl.seed,
                distractors=distractors,
            )
            h = np.array(st.height_m)
            te, re = np.array(st.translation_err_m), np.array(st.rotation_err_deg)
            band = (h >= 2) & (h <= 6)
            print(
                f"{args.random} random poses, {distractors} distractor dots: {st.visible} with "
                f"all marks in view, {st.correct} correct vertex maps, {st.wrong} wrong, "
                f"pose rate {100 * st.pose_rate:.2f} %, refused {dict(st.refused)}; "
                f"2-6 m: translation RMSE {100 * np.sqrt(np.mean(te[band] ** 2)):.2f} cm, "
                f"orientation RMSE {np.sqrt(np.mean(re[band] ** 2)):.3f} deg; "
                f"6-8 m: {100 * np.sqrt(np.mean(te[~band] ** 2)):.2f} cm, "
                f"{np.sqrt(np.mean(re[~band] ** 2)):.3f} deg"
            )
        return EXIT_OK
    from companion.offline import run_dpose
    from companion.reporting import write_dpose
    from sitl.scenario import Scenario

    s = cfg.sitl
    name = f"sitl-{s.terrain}-{s.trajectory}-{s.seconds:g}s-seed{s.seed}"
    out = Path(args.out) if args.out else Path("out") / "eval" / f"{name}-dpose"
    out.mkdir(parents=True, exist_ok=True)
    run = run_dpose(cfg, Scenario(cfg), DPOSE_ARM_S)
    table = write_dpose(run, out, f"d-Pose on {name}")
    ms = np.array(run.dpose_ms)
    print(table)
    print(
        f"d-Pose cost per frame: median {np.median(ms):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms"
    )
    print(f"tables and plot in {out}")
    return EXIT_OK


def cmd_eval(args: argparse.Namespace) -> int:
    """Run the pipeline over a dataset and write trajectories (TUM) and metrics."""
    import json

    if args.dpose:
        return cmd_eval_dpose(args)
    if args.attitude:
        return cmd_eval_attitude(args)
    if args.methods == "all":
        return cmd_eval_scale(args)

    import numpy as np

    from companion.offline import run_vo, vo_metrics
    from drivers.dataset import open_dataset, write_tum

    gt_poses: dict[int, Any] = {}
    gt_at: Callable[[int], Any]
    if args.dataset is not None:
        ds = open_dataset(args.dataset)
        cfg = ds.config or load_config(args.config)
        name = ds.path.name
        total = len(ds)
        events: Any = ds.events()
        camera, T_body_cam = ds.camera, ds.T_body_cam
        has_gt = len(ds.gt_times_us) > 0
        gt_at = ds.gt_pose_at
    else:  # straight from the simulator, no dataset on disk
        from sitl.scenario import Scenario

        cfg = _load(args)
        s = cfg.sitl
        name = f"sitl-{s.terrain}-{s.trajectory}-{s.seconds:g}s-seed{s.seed}"
        scenario = Scenario(cfg)
        total = scenario.n_frames
        events = _scenario_events(scenario, gt_poses)
        camera, T_body_cam = None, None
        has_gt = True
        gt_at = gt_poses.__getitem__
    out = Path(args.out) if args.out else Path("out") / "eval" / name
    out.mkdir(parents=True, exist_ok=True)
    bar = _progress(total, f"eval {name}", not args.no_progress)
    run = run_vo(cfg, events, _ticks(bar), camera=camera, T_body_cam=T_body_cam)
    bar.close()
    times = np.array(run.time_us)
    track = run.tracking_mask()
    T_est = np.array(run.T_vo_cam)
    write_tum(out / "vo.tum", times[track] * 1e-6, T_est[track])
    if has_gt:  # the camera's true trajectory, to compare with the VO's camera poses
        T_body_cam_gt = cfg.camera.T_body_cam() if T_body_cam is None else T_body_cam
        gt = np.array([gt_at(int(t)) @ T_body_cam_gt for t in times])
        write_tum(out / "groundtruth.tum", times * 1e-6, gt)
        m = vo_metrics(run, gt[:, :3, 3])
        metrics = {k: getattr(m, k) for k in m.__slots__}
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        rows = [
            f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |"
            for k, v in metrics.items()
        ]
        table = "\n".join(["| metric | value |", "|---|---|", *rows])
        (out / "report.md").write_text(f"# VO on {name}\n\n{table}\n")
        print(table)
    print(f"trajectories and metrics in {out}")
    return EXIT_OK


def cmd_bench_attitude(args: argparse.Namespace) -> int:
    """Benchmark the roll/pitch step (range tilt, compensation, fusion) per frame, one core:
    the frames of a SITL flight are recorded first, then the step alone is timed on them."""
    import time

    import cv2
    import numpy as np

    from companion.attitude.estimator import RollPitch
    from companion.bench import machine_description
    from companion.offline import run_attitude
    from sitl.scenario import Scenario

    cv2.setNumThreads(1)
    cfg = _load(args)
    scenario = Scenario(cfg)
    bar = _progress(scenario.n_frames, "bench attitude", not args.no_progress)
    run = run_attitude(cfg, scenario.steps(), _ticks(bar), keep_frames=True)
    bar.close()
    specs = {r.sensor_id: r.spec() for r in cfg.rangefinders}
    inputs = []
    pipe_ranges = run.ranges_used
    for (time_us, cloud, segment, _, _), ranges in zip(run.frames, pipe_ranges, strict=True):
        inputs.append((time_us, ranges, cloud, segment))
    est = RollPitch(specs, cfg.attitude)
    ms = []
    for time_us, ranges, cloud, segment in inputs:
        t0 = time.perf_counter()
        est.step(time_us, ranges, cloud, segment)
        ms.append((time.perf_counter() - t0) * 1e3)
    a = np.array(ms)
    points = np.median([len(c.points_m) for _, _, c, _ in inputs])
    print(f"machine: {machine_description()}")
    s = cfg.sitl
    print(
        f"roll/pitch step on {s.terrain}/{s.trajectory} {s.seconds:g} s "
        f"({len(a)} frames, {len(specs)} sensors, median {points:.0f} cloud points): "
        f"median {np.median(a):.3f} ms, p99 {np.percentile(a, 99):.3f} ms, "
        f"max {a.max():.3f} ms"
    )
    return EXIT_OK


def _exit_on_sigterm() -> None:
    """SIGTERM ends the command through SystemExit, so that ``finally`` blocks run (the SITL
    camera process and the soak's service are stopped, not orphaned on their ports)."""
    import signal

    def stop(signum: int, _frame: Any) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)


def cmd_bench_soak(args: argparse.Namespace) -> int:
    """The soak benchmark (sitl/soak.py): prints its figures, writes out/soak/soak.json."""
    import json

    from companion.bench import machine_description
    from sitl.soak import run_soak

    if args.minutes <= 0:
        raise ConfigError(f"--minutes: must be > 0, got {args.minutes}")
    _load(args)  # a bad config stops here
    print(f"machine: {machine_description()}", flush=True)
    print(f"soak: {args.minutes:g} min circle flight, service as its own process", flush=True)
    _exit_on_sigterm()
    result = run_soak(args.minutes, args.out, str(args.config))
    print(json.dumps(result, indent=2, default=str))
    return EXIT_OK


def cmd_bench_dpose(args: argparse.Namespace) -> int:
    """Benchmark d-Pose per frame (detection, vertex map, pose) on one core: the frames of a
    spiral flight over painted marks are rendered first, then only Dpose.step is timed."""
    import time

    import cv2
    import numpy as np

    from companion.bench import machine_description
    from companion.dpose.estimator import Dpose
    from companion.geometry import so3
    from sitl.scenario import Scenario

    cv2.setNumThreads(1)
    cfg = _dpose_config(args)
    sc = Scenario(cfg)
    specs = {r.sensor_id: r.spec() for r in cfg.rangefinders}
    dpose = Dpose(cfg.camera.model(), cfg.camera.T_body_cam(), specs)

    frames = []
    for st in sc.steps(start=30):
        R = st.T_world_body[:3, :3]
        if not dpose.armed:
            dpose.arm(sc.ranges.valid_at(st.frame.time_us), st.T_world_body, R)
        frames.append(
            (
                st.frame,
                R @ so3.exp(np.radians(0.1) * np.ones(3)),
                sc.ranges.valid_at(st.frame.time_us),
            )
        )
    ms, found = [], 0
    for frame, R_ap, ranges in frames:
        t0 = time.perf_counter()
        res = dpose.step(frame.time_us, frame.image_bgr, R_ap, ranges)
        ms.append((time.perf_counter() - t0) * 1e3)
        found += res is not None
    a = np.array(ms)
    print(f"machine: {machine_description()}")
    print(
        f"d-Pose step on {cfg.sitl.terrain}/spiral ({len(a)} frames, 640x480, one core): "
        f"median {np.median(a):.2f} ms, p99 {np.percentile(a, 99):.2f} ms, max {a.max():.2f} ms; "
        f"pose in {100 * found / len(a):.1f} % of frames"
    )
    return EXIT_OK


def cmd_bench_vo(args: argparse.Namespace) -> int:
    """Benchmark the VO: per-frame time on one core (median, p99) and peak RSS."""
    import cv2
    import numpy as np

    from companion.bench import machine_description
    from companion.offline import run_vo

    cv2.setNumThreads(1)
    if args.dataset is not None:
        from drivers.dataset import open_dataset

        ds = open_dataset(args.dataset)
        cfg = ds.config or load_config(args.config)
        events: Any = ds.events()
        total = len(ds)
        name = str(args.dataset)
        camera, T_body_cam = ds.camera, ds.T_body_cam
    else:
        from sitl.scenario import Scenario

        cfg = _load(args)
        scenario = Scenario(cfg)
        events = _scenario_events(scenario)
        total = scenario.n_frames
        name = f"sitl {cfg.sitl.terrain}/{cfg.sitl.trajectory} {cfg.sitl.seconds:g} s"
        camera, T_body_cam = None, None
    bar = _progress(total, "bench vo", not args.no_progress)
    run = run_vo(cfg, events, _ticks(bar), camera=camera, T_body_cam=T_body_cam)
    bar.close()
    ms = np.array(run.frame_ms)
    kf = np.array(run.keyframe)
    print(f"machine: {machine_description()}")
    print(f"input: {name}, {len(ms)} frames, one core (cv2.setNumThreads(1))")
    print(
        f"frame time: median {np.median(ms):.2f} ms ({1000 / np.median(ms):.0f} fps), "
        f"p99 {np.percentile(ms, 99):.2f} ms, max {ms.max():.1f} ms"
    )
    total_ms = np.array(run.total_ms)
    print(
        f"with the keyframe work after the pose: median {np.median(total_ms):.2f} ms, "
        f"p99 {np.percentile(total_ms, 99):.2f} ms"
    )
    if kf.any():  # the keyframe flag is on the frame after the one that built it
        built = np.roll(kf, -1)
        print(f"keyframes: {int(kf.sum())}, work median {np.median(total_ms[built]):.2f} ms")
    sc = np.array(run.scale_ms)[run.tracking_mask()]
    if len(sc):
        print(
            f"scale ({cfg.scale.method}, {len(cfg.rangefinders)} sensors, within the frame "
            f"time): median {np.median(sc):.3f} ms, p99 {np.percentile(sc, 99):.3f} ms"
        )
    print(f"tracking: {run.tracking_mask().mean():.3f} of frames, resets {run.resets}")
    print(f"peak RSS: {run.peak_rss_mb:.0f} MB")
    return EXIT_OK


def cmd_run(args: argparse.Namespace) -> int:
    """The service: camera + rangefinders + autopilot link -> pose messages, until SIGTERM /
    SIGINT or --duration."""
    import asyncio
    import logging
    import signal

    from companion.config import describe
    from companion.redact import redact_url
    from companion.service.app import Service

    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    log = logging.getLogger("companion")
    cfg = _load(args)
    for line in describe(cfg):
        log.debug("config %s", line)
    s = cfg.service
    log.info("link %s, camera %s, output %s", s.mavlink_url, redact_url(s.camera_url), s.output)
    report = args.report or s.report_path

    async def serve() -> dict[str, Any]:
        service = Service(cfg)  # a bad URL raises ConfigError here, before anything starts
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, service.stop)
        async with service:
            await service.run(args.duration)
        summary = service.summary()
        if report:
            try:
                service.write_report(Path(report))
            except OSError as e:  # a full disk: the run itself went fine
                log.warning("exit report not written to %s: %s", report, e)
        return summary

    summary = asyncio.run(serve())
    log.info(
        "published %d poses (%.1f Hz), %d frames in, %d dropped, latency p50 %s ms",
        summary["published"],
        summary["publish_rate_hz"],
        summary["frames_in"],
        summary["frames_dropped"],
        f"{summary['latency_ms_p50']:.1f}" if summary["latency_ms_p50"] is not None else "-",
    )
    return EXIT_OK


EXIT_NOT_RUNNING = 3  # as `systemctl status` for a unit that is not active


def _mqtt_line(m: dict[str, Any]) -> str:
    if not m.get("enabled"):
        return "disabled"
    state = "connected" if m.get("connected") else "NOT connected"
    return f"{state}, {m.get('queued', 0)} queued, {m.get('dropped', 0)} dropped"


def _signing_text(ap: dict[str, Any]) -> str:
    sg = ap.get("signing")
    if not sg:
        return ", unsigned link"
    return f", signed: {sg['good_signatures']} good, {sg['bad_signatures']} bad signatures, " + (
        f"{sg['refused']} refused"
    )


def format_status(st: dict[str, Any]) -> str:
    """The status JSON as a readable table (plain text, aligned)."""

    def fmt(v: Any, unit: str = "", digits: int = 2) -> str:
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.{digits}f}{unit}"
        return f"{v}{unit}"

    ap, cam, vo, sc, att, out = (
        st["autopilot"],
        st["camera"],
        st["vo"],
        st["scale"],
        st["attitude"],
        st["output"],
    )
    rows = [
        ("uptime", fmt(st["uptime_s"], " s", 0)),
        (
            "autopilot",
            f"{ap['url']}  system {fmt(ap['system_id'])}  heartbeat "
            f"{fmt(ap['heartbeat_age_s'], ' s ago', 1)}",
        ),
        (
            "  time sync",
            f"{'converged' if ap['timesync_converged'] else 'NOT converged'}  "
            f"offset {fmt(ap['timesync_offset_ms'], ' ms', 3)}  "
            f"rtt {fmt(ap['timesync_rtt_ms'], ' ms', 2)}",
        ),
        ("  messages", f"{ap['rx_messages']} in, {ap['rx_bad']} bad" + _signing_text(ap)),
        (
            "camera",
            f"{cam['url']}  {fmt(cam['fps'], ' fps', 1)}  {cam['frames']} frames, "
            f"{cam['dropped']} dropped, last {fmt(cam['last_frame_age_s'], ' s ago', 2)}"
            + (
                f", stamped at {cam['stamps']}"
                if cam.get("stamps") in ("grab", "v4l2 buffer")
                else ""
            )
            + (f"  NOW {cam['problem'].upper()} FRAMES" if cam.get("problem") else "")
            + "".join(f", {n} {k}" for k, n in (cam.get("rejected") or {}).items()),
        ),
        (
            "VO",
            f"{vo['state']}  {vo['features']} features  {vo['keyframes']} keyframes  "
            f"{vo['resets']} resets",
        ),
        (
            "scale",
            f"{sc['method']}  {fmt(sc['value'], '', 4)} ± {fmt(sc['sigma'], '', 4)}  "
            f"{sc['sensors_used']} sensors  ranges {sc['ranges_in']} in, "
            f"{sc['ranges_rejected']} rejected",
        ),
        (
            "  matches",
            "  ".join(
                f"sensor {k} {100 * v:.0f} %" for k, v in (sc.get("match_rate") or {}).items()
            )
            or "-",
        ),
        (
            "roll/pitch",
            f"{fmt(att['roll_deg'], '°')} / {fmt(att['pitch_deg'], '°')}  "
            f"± {fmt(att['sigma_deg'], '°', 3)}  "
            f"compensation {'on' if att['compensation'] else 'off'}",
        ),
        (
            "output",
            f"{out['message']}  {fmt(out['rate_hz'], ' Hz', 1)}  {out['published']} sent  "
            f"reset_counter {out['reset_counter']}  "
            f"latency p50 {fmt(out['latency_ms_p50'], ' ms', 1)}",
        ),
        ("MQTT", _mqtt_line(st["mqtt"])),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    warnings = st.get("warnings") or []
    lines.append(f"{'warnings':<{width}}  " + ("none" if not warnings else warnings[-1]))
    lines.extend(f"{'':<{width}}  {w}" for w in warnings[-5:-1][::-1])
    for r in att.get("reasons", [])[:3]:
        lines.append(f"{'':<{width}}  roll/pitch: {r}")
    return "\n".join(lines)


def cmd_status(args: argparse.Namespace) -> int:
    """Show the running service's state (exit 3 when it is not running)."""
    import json
    import time

    from companion.service.status import read_status, status_path

    path = Path(args.socket) if args.socket else status_path(_load(args).service.status_socket)
    while True:
        st = read_status(path)
        if st is None:
            print(f"companion is not running (no service on {path})")
            return EXIT_NOT_RUNNING
        text = json.dumps(st, indent=2) if args.json else format_status(st)
        if args.watch:
            print("\033[H\033[2J" + text, flush=True)
            time.sleep(1.0)
            continue
        print(text)
        return EXIT_OK


def cmd_sitl_run(args: argparse.Namespace) -> int:
    """The PX4-like SITL autopilot with its camera stream (sitl/autopilot.py)."""
    import asyncio
    import json

    from drivers.signing import load_key
    from sitl.autopilot import AutopilotOptions, SimAutopilot
    from sitl.faults import Fault

    cfg = _load(args)
    out = Path(args.out) if args.out else Path("out") / "sitl-run"
    faults = tuple(Fault.parse(f) for f in args.fault or ())
    key = load_key(args.signing_key, "--signing-key") if args.signing_key else b""
    stub = SimAutopilot(
        cfg, AutopilotOptions(prerender=args.prerender, faults=faults, signing_key=key)
    )
    for f in faults:
        print(f"fault: {f.kind} at {f.start_s:g} s for {f.duration_s:g} s", flush=True)
    print(
        f"SITL autopilot: {cfg.sitl.terrain}/{cfg.sitl.trajectory} {cfg.sitl.seconds:g} s, "
        f"listening on 127.0.0.1:{stub.opts.listen_port}, sending to "
        f"127.0.0.1:{stub.opts.companion_port}, camera on tcp 127.0.0.1:{stub.opts.camera_port}; "
        f"ground station (`companion px4 check --url udpin://127.0.0.1:{stub.opts.gcs_port}`) "
        f"from udp {stub.opts.gcs_listen_port} to {stub.opts.gcs_port}",
        flush=True,
    )
    if args.prerender:
        print("rendering every camera frame before the flight (about a minute)...", flush=True)
    _exit_on_sigterm()
    report = asyncio.run(stub.run(out))
    print(json.dumps(report, indent=2))
    print(f"report, received.csv and plot in {out}")
    return EXIT_OK


def cmd_demo(args: argparse.Namespace) -> int:
    """SITL autopilot + service together on the SITL default; prints what the autopilot saw."""
    import json
    import subprocess

    _load(args)  # a bad config stops here (exit 2), before any process is started
    out = Path(args.out) if args.out else Path("out") / "demo"
    out.mkdir(parents=True, exist_ok=True)
    common = []
    if args.config:
        common += ["--config", str(args.config)]
    for flag in ("terrain", "trajectory", "seconds", "seed"):
        v = getattr(args, flag, None)
        if v is not None:
            common += [f"--{flag}", str(v)]
    py = [sys.executable, "-m", "companion.cli"]
    extra = ["--prerender"] if args.prerender else []
    stub = subprocess.Popen([*py, "sitl", "run", *common, *extra, "--out", str(out / "autopilot")])
    service = subprocess.Popen([*py, "run", *common, "--report", str(out / "service.json")])
    rc_stub = stub.wait()  # the flight is over: stop the service as systemd would (SIGTERM)
    service.terminate()
    rc_service = service.wait()
    if rc_service or rc_stub:
        raise CompanionError(f"demo failed: service exit {rc_service}, autopilot exit {rc_stub}")
    rep = json.loads((out / "autopilot" / "report.json").read_text())
    svc = json.loads((out / "service.json").read_text())
    if "error" in rep:
        raise CompanionError(f"demo: the autopilot says: {rep['error']}")
    print()
    print(
        f"received by the autopilot: {rep['received']} {rep['message']} at "
        f"{rep['received_rate_hz']:.1f} Hz"
    )
    print(
        f"end-to-end latency (exposure -> autopilot): p50 {rep['latency_ms_p50']:.1f} ms, "
        f"p99 {rep['latency_ms_p99']:.1f} ms"
    )
    print(
        f"metric ATE seen by the autopilot (SE3, its clock): {rep['ate_m']:.3f} m = "
        f"{rep['ate_pct']:.2f} % of {rep['path_m']:.0f} m; "
        f"scale error {rep['scale_error_pct']:+.2f} %"
    )
    print(
        f"time sync: conversion error max {rep['timesync_error_ms_max']:.3f} ms; TIMESYNC "
        f"round trip p99 {rep.get('timesync_rtt_ms_p99', float('nan')):.2f} ms"
    )
    print(
        f"service: {svc['frames_in']} frames, {svc['frames_dropped']} dropped, "
        f"capture-to-send p50 {svc['latency_ms_p50']:.1f} ms, p99 {svc['latency_ms_p99']:.1f} ms"
    )
    print(f"plots and logs: {out / 'autopilot' / 'autopilot.png'}, {out}")
    return EXIT_OK


def _scenario_events(scenario: Any, gt_poses: dict[int, Any] | None = None) -> Iterator[Any]:
    """The simulator's inputs in time order (attitude and ranges before their frame); the
    true body pose of each frame goes to ``gt_poses`` by time."""
    for step in scenario.steps():
        if gt_poses is not None:
            gt_poses[step.frame.time_us] = step.T_world_body
        yield from step.attitudes
        for r in step.ranges:
            if r.sample is not None:
                yield r.sample
        yield step.frame


def _add_sitl_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, help="TOML config file (default: built-in SITL)")
    p.add_argument("--terrain", choices=["flat", "hills", "urban", "slope"])
    p.add_argument("--trajectory", choices=["hover", "circle", "lawnmower", "figure8", "climb"])
    p.add_argument("--seconds", type=float, help="flight duration [s]")
    p.add_argument("--seed", type=int)
    p.add_argument("--altitude", type=float, help="height above ground [m] (0 = terrain default)")
    p.add_argument("--speed", type=float, help="cruise speed [m/s]")
    p.add_argument("--takeoff-landing", action="store_true", help="take off and land")
    p.add_argument("--laser-marks", choices=["off", "live", "painted"])


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``companion``."""
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"companion {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p_cfg = sub.add_parser("config", help="print the effective configuration")
    p_cfg.add_argument("--config", type=Path)
    p_cfg.set_defaults(func=cmd_config)

    p_sitl = sub.add_parser("sitl", help="the simulator")
    sitl_sub = p_sitl.add_subparsers(dest="sitl_command", required=True)
    p_rec = sitl_sub.add_parser("record", help="record a dataset")
    _add_sitl_flags(p_rec)
    p_rec.add_argument("--out", type=Path, required=True, help="output folder")
    p_rec.add_argument("--image-format", choices=["jpg", "png"], default="jpg")
    p_rec.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    p_rec.add_argument("--no-progress", action="store_true", help="no progress bar")
    p_rec.set_defaults(func=cmd_sitl_record)
    p_srun = sitl_sub.add_parser("run", help="the PX4-like SITL autopilot with its camera")
    _add_sitl_flags(p_srun)
    p_srun.add_argument("--out", type=Path, help="report folder (default out/sitl-run)")
    p_srun.add_argument(
        "--prerender", action="store_true", help="render every frame before the flight"
    )
    p_srun.add_argument(
        "--fault",
        action="append",
        metavar="KIND@START+DURATION",
        help="inject a fault (repeatable): camera_freeze, camera_black, camera_saturated, "
        "camera_unplug, link_silence, link_port_change, autopilot_reboot (sitl/faults.py)",
    )
    p_srun.add_argument(
        "--signing-key", help="sign with this 32-byte key file and refuse unsigned frames"
    )
    p_srun.set_defaults(func=cmd_sitl_run)
    p_px4 = sitl_sub.add_parser("px4", help="fly the real PX4 SITL (SIH) on our estimate")
    p_px4.add_argument("--px4", help="PX4 SITL launcher (else $PX4_SITL, ../shared/px4-sitl)")
    p_px4.add_argument("--mission", choices=["square", "lawnmower", "hover"], default="square")
    p_px4.add_argument("--seed", type=int, default=1, help="world and sensor noise seed")
    p_px4.add_argument("--instance", type=int, default=0, help="PX4 instance (ports shift by it)")
    p_px4.add_argument("--config", type=Path, help="default: config/px4_sitl.toml")
    p_px4.add_argument("--no-configure", action="store_true", help="skip `companion px4 configure`")
    p_px4.add_argument("--out", type=Path, required=True, help="output folder")
    p_px4.set_defaults(func=lambda a: __import__("sitl.px4_flight").px4_flight.cli_main(a))
    p_sheet = sitl_sub.add_parser("sheet", help="write a PNG contact sheet of a dataset")
    p_sheet.add_argument("dataset", type=Path)
    p_sheet.add_argument("--out", type=Path)
    p_sheet.set_defaults(func=cmd_sitl_sheet)

    p_bench = sub.add_parser("bench", help="benchmarks")
    bench_sub = p_bench.add_subparsers(dest="bench_command", required=True)
    p_br = bench_sub.add_parser("render", help="SITL rendering speed on one core")
    p_br.add_argument("--config", type=Path)
    p_br.add_argument("--terrains", nargs="+", default=["flat", "hills", "urban", "slope"])
    p_br.add_argument("--frames", type=int, default=300, help="frames per terrain")
    p_br.set_defaults(func=cmd_bench_render)
    p_bv = bench_sub.add_parser("vo", help="VO speed and memory on one core")
    p_bv.add_argument("dataset", type=Path, nargs="?", help="dataset folder (default: SITL)")
    _add_sitl_flags(p_bv)
    p_bv.add_argument("--no-progress", action="store_true")
    p_bv.set_defaults(func=cmd_bench_vo)
    p_ba = bench_sub.add_parser("attitude", help="roll/pitch cost per range update, one core")
    _add_sitl_flags(p_ba)
    p_ba.add_argument("--no-progress", action="store_true")
    p_ba.set_defaults(func=cmd_bench_attitude)
    p_bd = bench_sub.add_parser("dpose", help="d-Pose cost per frame, one core")
    _add_sitl_flags(p_bd)
    p_bd.set_defaults(func=cmd_bench_dpose)
    p_bs = bench_sub.add_parser(
        "soak", help="the service process against the SITL for a long flight: memory, drops"
    )
    p_bs.add_argument("--minutes", type=float, default=30.0, help="flight length [min]")
    p_bs.add_argument("--config", type=Path, default=Path("config/sitl.toml"))
    p_bs.add_argument("--out", type=Path, default=Path("out/soak"))
    p_bs.set_defaults(func=cmd_bench_soak)

    p_rep = sub.add_parser("report", help="summarise scale evaluations over seeds")
    p_rep.add_argument("dirs", nargs="+", type=Path)
    p_rep.set_defaults(func=cmd_report)

    p_run = sub.add_parser("run", help="the service (camera + rangefinders -> autopilot)")
    p_run.add_argument("--config", type=Path, help="TOML config file (default: built-in SITL)")
    p_run.add_argument("--duration", type=float, help="stop after this many seconds")
    p_run.add_argument("--report", type=Path, help="write a JSON summary here on exit")
    p_run.add_argument("--terrain", help=argparse.SUPPRESS)
    p_run.add_argument("--trajectory", help=argparse.SUPPRESS)
    p_run.add_argument("--seconds", type=float, help=argparse.SUPPRESS)
    p_run.add_argument("--seed", type=int, help=argparse.SUPPRESS)
    p_run.set_defaults(func=cmd_run)

    p_status = sub.add_parser("status", help="the running service's state (exit 3 if none)")
    p_status.add_argument("--config", type=Path, help="TOML config (for service.status_socket)")
    p_status.add_argument("--socket", type=Path, help="status socket path")
    p_status.add_argument("--json", action="store_true", help="JSON for machines")
    p_status.add_argument("--watch", action="store_true", help="refresh every second")
    p_status.set_defaults(func=cmd_status)

    p_demo = sub.add_parser("demo", help="SITL autopilot + service together, with a summary")
    _add_sitl_flags(p_demo)
    p_demo.add_argument("--out", type=Path, help="output folder (default out/demo)")
    p_demo.add_argument(
        "--prerender",
        action="store_true",
        help="render the camera before the flight (latency without the renderer's CPU load)",
    )
    p_demo.set_defaults(func=cmd_demo)

    p_eval = sub.add_parser("eval", help="evaluate the pipeline on a dataset or a SITL flight")
    p_eval.add_argument("dataset", type=Path, nargs="?", help="dataset folder (default: SITL)")
    _add_sitl_flags(p_eval)
    p_eval.add_argument("--out", type=Path, help="output folder (default out/eval/NAME)")
    p_eval.add_argument(
        "--methods",
        choices=["vo", "all"],
        default="vo",
        help="vo: the odometry alone; all: every scale method (SITL)",
    )
    p_eval.add_argument(
        "--sensor-study", action="store_true", help="with --methods all: M-MSC with 1..6 sensors"
    )
    p_eval.add_argument(
        "--attitude", action="store_true", help="roll/pitch from the distance sensors (SITL)"
    )
    p_eval.add_argument(
        "--spacing", type=float, help="--attitude: 3 sensors on a triangle of this side [m]"
    )
    p_eval.add_argument(
        "--range-sigma", type=float, default=0.01, help="--attitude: range noise sigma [m]"
    )
    p_eval.add_argument(
        "--study", action="store_true", help="--attitude: RMSE vs sensor spacing and range noise"
    )
    p_eval.add_argument(
        "--dpose", action="store_true", help="d-Pose over painted laser marks (SITL, spiral)"
    )
    p_eval.add_argument(
        "--random", type=int, default=0, help="--dpose: N random synthetic poses instead"
    )
    p_eval.add_argument("--no-progress", action="store_true")
    p_eval.set_defaults(func=cmd_eval)

    from companion.calibration.cli import add_parser as add_calibrate_parser

    add_calibrate_parser(sub)  # companion calibrate board | intrinsics | lasers | sim-*

    from companion.px4.cli import add_parser as add_px4_parser

    add_px4_parser(sub)  # companion px4 check | configure
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``companion`` console script; returns the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # argparse exits 2 on bad usage, 0 for --help
        return int(e.code) if isinstance(e.code, int) else EXIT_CONFIG
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except ConfigError as e:
        print(f"companion: config error: {e}", file=sys.stderr)
        return EXIT_CONFIG
    except CompanionError as e:
        print(f"companion: error: {e}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("companion: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
