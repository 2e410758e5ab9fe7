"""``companion bench render | vo | attitude | dpose | record | soak``: the figures of
docs/BENCHMARKS.md.

Simulated flights come through ``companion.cli.sim``; the Pipeline is imported inside the
commands, so that the other commands start without it.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion.bench import bench_render, format_render_report, machine_description
from companion.bench_vo import BOARD_FACTORS
from companion.cli import sim
from companion.cli.common import (
    EXIT_OK,
    EXIT_PROBLEMS,
    add_sitl_flags,
    dpose_config,
    exit_on_sigterm,
    load,
    progress,
)
from companion.cli.evaluate import vo_input
from companion.errors import ConfigError
from companion.geometry import so3


def cmd_bench_render(args: argparse.Namespace) -> int:
    """Benchmark SITL rendering (frames/s on one core)."""
    report = bench_render(load(args), args.terrains, args.frames, sim.scenario)
    print(format_render_report(report))
    return EXIT_OK


def cmd_bench_vo(args: argparse.Namespace) -> int:
    """Benchmark the pipeline on one core against its floor (companion/bench_vo.py): the
    floor line, the frame and keyframe times, the per-stage table, the worker's delays at the
    camera's rate, peak RSS; ``--profile``: cProfile of the run; ``--board``: an estimate."""
    from companion.bench_vo import BOARD_FACTORS, KltFloor, floor_ratios, stage_table, worker_delays
    from companion.offline import run_vo

    cv2.setNumThreads(1)
    inp = vo_input(
        args, lambda c: f"sitl {c.sitl.terrain}/{c.sitl.trajectory} {c.sitl.seconds:g} s"
    )
    name = str(args.dataset) if args.dataset is not None else inp.name
    floor = KltFloor(inp.cfg.vo.klt_window_px, inp.cfg.vo.klt_levels)
    profiler = cProfile.Profile() if args.profile is not None else None
    with progress(inp.total, "bench vo", not args.no_progress) as ticks:
        if profiler is not None:
            profiler.enable()
        run = run_vo(
            inp.cfg, inp.events, ticks, camera=inp.camera, T_body_cam=inp.T_body_cam, observe=floor
        )
        if profiler is not None:
            profiler.disable()
    ms = np.array(run.frame_ms)
    total_ms = np.array(run.total_ms)
    tracked = run.tracking_mask()
    built = np.roll(np.array(run.keyframe), -1)  # flagged on the frame after the one that built
    if not tracked.any() or not floor.ms:
        print(
            f"bench vo: the VO tracked no frame of {name} ({len(ms)} frames, resets "
            f"{run.resets}): no frame time to set against the floor",
            file=sys.stderr,
        )
        return EXIT_PROBLEMS
    ratios = floor_ratios(floor.ms, ms[tracked], total_ms[built & tracked])
    size = inp.camera or inp.cfg.camera  # a dataset's own calibration, else the config's
    w, h = size.width, size.height
    print(f"machine: {machine_description()}")
    print(f"input: {name}, {len(ms)} frames {w}x{h}, one core (cv2.setNumThreads(1))")
    if profiler is not None:
        print("(under cProfile: every time below is inflated by the profiler)")
    print(ratios.line())
    print(
        f"floor: OpenCV's pyramidal KLT of the VO's tracks after the frame before (median "
        f"{np.median(floor.features):.0f}), window {floor.window_px} px, {floor.levels} levels, "
        "no initial flow, pose solve not counted"
    )
    if floor.pnp_ms:  # the floor with the least pose solve added (companion/bench_vo.py)
        pnp_ms = float(np.median(floor.pnp_ms))
        posed = floor_ratios([ratios.floor_ms + pnp_ms], ms[tracked], total_ms[built & tracked])
        print(
            f"floor with the pose solve: KLT + OpenCV's iterative PnP of the frame's inliers "
            f"(median {pnp_ms:.2f} ms over {len(floor.pnp_ms)} frames) = {posed.floor_ms:.2f} "
            f"ms; frame median {posed.frame_ratio:.2f}x; p99 {posed.p99_ratio:.2f}x; keyframe "
            f"{posed.keyframe_ratio:.2f}x"
        )
    print(
        f"frame time (tracked frames, to the pose): median {ratios.frame_ms:.2f} ms "
        f"({1000 / ratios.frame_ms:.0f} fps), p99 {ratios.p99_ms:.2f} ms, max {ms.max():.1f} ms"
    )
    print(
        f"with the work after the pose: median {np.median(total_ms):.2f} ms, "
        f"p99 {np.percentile(total_ms, 99):.2f} ms; keyframes {int(built.sum())}, "
        f"work median {ratios.keyframe_ms:.2f} ms"
    )
    rate_hz = inp.cfg.camera.rate_hz
    delays = worker_delays(run.time_us, run.total_ms)
    print(
        f"worker at the camera's stamps (~{rate_hz:g} Hz; a model on the measured times): a "
        f"pose waits for the work before it at most {delays.delay_ms.max():.1f} ms, p99 "
        f"{np.percentile(delays.delay_ms, 99):.1f} ms; {delays.dropped} frames skipped"
    )
    print(f"tracking: {tracked.mean():.3f} of frames, resets {run.resets}")
    print(run.gc)
    print(f"peak RSS (this process, the simulator's world included): {run.peak_rss_mb:.0f} MB")
    print()
    print("\n".join(stage_table(run.stage_ms, run.frame_ms)))
    if args.board is not None:
        f = BOARD_FACTORS[args.board]
        print(
            f"\n{args.board}: ESTIMATE, not a measurement: x{f:g} (a planning factor for "
            f"OpenCV work on its core against this one): frame median ~{f * ratios.frame_ms:.0f} "
            f"ms, p99 ~{f * ratios.p99_ms:.0f} ms, keyframe ~{f * ratios.keyframe_ms:.0f} ms; "
            f"{rate_hz:g} Hz leaves {1000 / rate_hz:.1f} ms a frame"
        )
    if profiler is not None:
        stats = pstats.Stats(profiler, stream=sys.stdout)
        if args.profile:
            stats.dump_stats(args.profile)
            print(f"\nprofile written to {args.profile} (python -m pstats {args.profile})")
        print()
        stats.sort_stats("cumulative").print_stats(r"companion|cv2|\{", 30)
    return EXIT_OK


def cmd_bench_attitude(args: argparse.Namespace) -> int:
    """Benchmark the roll/pitch step (range tilt, compensation, fusion) per frame, one core:
    the frames of a SITL flight are recorded first, then the step alone is timed on them."""
    from companion.attitude.estimator import RollPitch
    from companion.offline import run_attitude

    cv2.setNumThreads(1)
    cfg = load(args)
    flight = sim.scenario(cfg)
    with progress(flight.n_frames, "bench attitude", not args.no_progress) as ticks:
        run = run_attitude(cfg, flight.steps(), ticks, keep_frames=True)
    specs = {r.sensor_id: r.spec() for r in cfg.rangefinders}
    inputs = [
        (time_us, ranges, cloud, segment)
        for (time_us, cloud, segment, _, _), ranges in zip(run.frames, run.ranges_used, strict=True)
    ]
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


def cmd_bench_dpose(args: argparse.Namespace) -> int:
    """Benchmark d-Pose per frame (detection, vertex map, pose) on one core: the frames of a
    spiral flight over painted marks are rendered first, then only Dpose.step is timed."""
    from companion.dpose.estimator import Dpose

    cv2.setNumThreads(1)
    cfg = dpose_config(args)
    flight = sim.scenario(cfg)
    specs = {r.sensor_id: r.spec() for r in cfg.rangefinders}
    dpose = Dpose(cfg.camera.model(), cfg.camera.T_body_cam(), specs)
    frames = []
    for st in flight.steps(start=30):
        R = st.T_world_body[:3, :3]
        if not dpose.armed:
            dpose.arm(flight.ranges.valid_at(st.frame.time_us), st.T_world_body, R)
        R_ap = R @ so3.exp(np.radians(0.1) * np.ones(3))
        frames.append((st.frame, R_ap, flight.ranges.valid_at(st.frame.time_us)))
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


def cmd_bench_soak(args: argparse.Namespace) -> int:
    """The soak benchmark (sitl/soak.py): prints its figures, writes out/soak/soak.json."""
    if args.minutes <= 0:
        raise ConfigError(f"--minutes: must be > 0, got {args.minutes}")
    load(args)  # a bad config stops here
    print(f"machine: {machine_description()}", flush=True)
    print(f"soak: {args.minutes:g} min circle flight, service as its own process", flush=True)
    exit_on_sigterm()
    result = sim.soak(args.minutes, args.out, str(args.config))
    print(json.dumps(result, indent=2, default=str))
    return EXIT_OK


RECORD_OPTIONS: tuple[tuple[str, dict[str, Any]], ...] = (  # `companion bench record`
    ("folder, PNG", {"format": "folder"}),
    ("MCAP, colour PNG", {"format": "mcap", "image": "colour"}),
    ("MCAP, grey PNG (auto)", {"format": "mcap", "image": "auto"}),
    ("MCAP, grey JPEG 95", {"format": "mcap", "image": "grey", "image_format": "jpg"}),
)


def cmd_bench_record(args: argparse.Namespace) -> int:
    """The flight recorder's size and writer CPU per frame, by [record] option: the first
    ``--frames`` frames of a dataset (with their samples) through a ``Recorder`` each, into
    a temporary folder; per minute = per frame x 1800 (30 Hz). The writer's CPU is its own
    thread's (``writer_cpu_s``): it does not depend on what else the machine runs."""
    import dataclasses
    import tempfile

    from companion.drivers.dataset import dataset_steps, open_dataset
    from companion.service.recorder import Recorder

    if args.frames < 1:
        raise ConfigError(f"--frames: must be >= 1, got {args.frames}")
    ds = open_dataset(args.dataset)
    steps = [s for _, s in zip(range(args.frames), dataset_steps(ds), strict=False)]
    if ds.config is None:
        raise ConfigError(f"{args.dataset}: not a dataset of ours (no calibration.toml)")
    base = load(args)
    base = dataclasses.replace(base, camera=ds.config.camera, rangefinders=ds.config.rangefinders)
    print(f"machine: {machine_description()}")
    print(f"{args.dataset}: {len(steps)} frames {ds.camera.width}x{ds.camera.height}")
    print("| option | size per frame | per minute at 30 Hz | writer CPU per frame | replay |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="bench-record-") as tmp:
        for k, (name, keys) in enumerate(RECORD_OPTIONS):
            record = dataclasses.replace(
                base.record, dir=f"{tmp}/rec{k}", queue_frames=len(steps) + 2, **keys
            )
            cfg = dataclasses.replace(base, record=record)
            with Recorder(record, cfg).running() as rec:
                for s in steps:
                    rec.frame(s.frame, [r.sample for r in s.ranges if r.sample], s.attitudes)
            st = rec.status()
            path = rec.path
            assert path is not None
            files = path.rglob("*") if path.is_dir() else [path]
            size = sum(f.stat().st_size for f in files if f.is_file()) / max(st["frames"], 1)
            exact = "exact" if record.image_format == "png" else "approximate"
            print(
                f"| {name} | {size / 1e3:.1f} kB | {size * 1800 / 1e9:.2f} GB | "
                f"{st['writer_cpu_s'] / max(st['frames'], 1) * 1e3:.1f} ms | {exact} |"
            )
    return EXIT_OK


def add_bench(sub: Any) -> None:
    """``companion bench render | vo | attitude | dpose | record | soak``."""
    p_bench = sub.add_parser("bench", help="benchmarks")
    bench_sub = p_bench.add_subparsers(dest="bench_command", required=True)
    p_br = bench_sub.add_parser("render", help="SITL rendering speed on one core")
    p_br.add_argument("--config", type=Path, help="TOML config file (default: built-in SITL)")
    p_br.add_argument(
        "--terrains",
        nargs="+",
        default=["flat", "hills", "urban", "slope"],
        help="terrains to render (default: all four)",
    )
    p_br.add_argument("--frames", type=int, default=300, help="frames per terrain")
    p_br.set_defaults(func=cmd_bench_render)
    p_bv = bench_sub.add_parser("vo", help="VO speed and memory on one core")
    p_bv.add_argument("dataset", type=Path, nargs="?", help="dataset folder (default: SITL)")
    add_sitl_flags(p_bv)
    p_bv.add_argument("--no-progress", action="store_true", help="no progress bar")
    p_bv.add_argument(
        "--profile",
        nargs="?",
        const="",
        metavar="FILE",
        help="run under cProfile, print the top functions (and write FILE.prof if given)",
    )
    p_bv.add_argument(
        "--board",
        choices=sorted(BOARD_FACTORS),
        help="also print the planning estimate for a Raspberry Pi 4 (x5) or 5 (x2.5)",
    )
    p_bv.set_defaults(func=cmd_bench_vo)
    p_ba = bench_sub.add_parser("attitude", help="roll/pitch cost per range update, one core")
    add_sitl_flags(p_ba)
    p_ba.add_argument("--no-progress", action="store_true", help="no progress bar")
    p_ba.set_defaults(func=cmd_bench_attitude)
    p_bd = bench_sub.add_parser("dpose", help="d-Pose cost per frame, one core")
    add_sitl_flags(p_bd)
    p_bd.set_defaults(func=cmd_bench_dpose)
    p_brec = bench_sub.add_parser(
        "record", help="the flight recorder's size and writer CPU per frame, by [record] option"
    )
    p_brec.add_argument("dataset", type=Path, help="a dataset (e.g. `companion sitl record`)")
    p_brec.add_argument("--config", type=Path, help="TOML config file (default: built-in)")
    p_brec.add_argument("--frames", type=int, default=300, help="frames recorded per option")
    p_brec.set_defaults(func=cmd_bench_record)
    p_bs = bench_sub.add_parser(
        "soak", help="the service process against the SITL for a long flight: memory, drops"
    )
    p_bs.add_argument("--minutes", type=float, default=30.0, help="flight length [min]")
    p_bs.add_argument(
        "--config",
        type=Path,
        default=Path("config/sitl.toml"),
        help="the service's config (default config/sitl.toml)",
    )
    p_bs.add_argument(
        "--out", type=Path, default=Path("out/soak"), help="output folder (default out/soak)"
    )
    p_bs.set_defaults(func=cmd_bench_soak)
