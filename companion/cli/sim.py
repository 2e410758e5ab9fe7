"""The simulator's commands, and the one place where the product reaches the simulator.

``companion sitl record | sheet | run | px4 | ardupilot`` and ``companion demo`` live here. The
other command modules get simulator objects (a flight, its events, a recorded flight's world, the
soak, synthetic calibration input) only through the functions below: no other module of
``companion`` imports ``sitl`` (docs/architecture.md). ``sitl`` is imported inside them, so
``companion run | status | config`` never load the simulator (numba, the renderer).
"""

from __future__ import annotations

import argparse
import asyncio
import importlib
import json
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np
from numpy.typing import NDArray

from companion.cli.common import EXIT_OK, add_sitl_flags, exit_on_sigterm, load
from companion.config import Config, RangefinderConfig
from companion.drivers.dataset import Dataset, open_dataset
from companion.drivers.signing import load_key
from companion.errors import CompanionError
from companion.geometry.camera import CameraModel
from companion.types import AttitudeSample, CameraFrame, RangeSample

if TYPE_CHECKING:
    from companion.calibration_maths.board import BoardSpec
    from companion.calibration_maths.lasers import LaserFrame
    from companion.sitl.world.scenario import Scenario
    from companion.sitl.world.sensors import RangeSimulator
    from companion.sitl.world.terrain import World

Event = CameraFrame | RangeSample | AttitudeSample
Flight: TypeAlias = "Scenario"  # a simulated flight, for the other command modules' annotations


# ------------------------------------------------------------------------------ the gateway
def scenario(cfg: Config) -> Flight:
    """The simulated flight of ``cfg.sitl`` with the sensors of ``cfg``."""
    from companion.sitl.world.scenario import Scenario

    return Scenario(cfg)


def flight_events(sc: Flight, gt_poses: dict[int, Any] | None = None) -> Iterator[Event]:
    """The simulator's inputs in time order (attitude and ranges before their frame); the
    true body pose of each frame goes to ``gt_poses`` by time."""
    for step in sc.steps():
        if gt_poses is not None:
            gt_poses[step.frame.time_us] = step.T_world_body
        yield from step.attitudes
        for r in step.ranges:
            if r.sample is not None:
                yield r.sample
        yield step.frame


def recorded_world(ds: Dataset) -> World:
    """The world of a recorded SITL flight, rebuilt from its meta.toml."""
    from companion.sitl.world.terrain import make_world

    assert ds.sitl is not None
    s = ds.sitl
    return make_world(s.terrain, s.seed, s.world_size_m, s.height_resolution_m, s.ground)


def range_simulator(
    sc: Flight, rangefinders: Sequence[RangefinderConfig], seed: int
) -> RangeSimulator:
    """Other distance sensors over the same flight (``valid_at(time_us)``: their readings)."""
    from companion.sitl.world.sensors import RangeSimulator

    return RangeSimulator(sc.world, sc.trajectory, rangefinders, seed, sc.cfg.sitl.rangefinder)


def soak(minutes: float, out: Path, config: str) -> dict[str, Any]:
    """The soak flight (sitl/stub/soak.py): the service as its own process against the SITL."""
    from companion.sitl.stub.soak import run_soak

    return run_soak(minutes, out, config)


def board_photos(
    camera: CameraModel, spec: BoardSpec, views: int, seed: int
) -> list[NDArray[np.uint8]]:
    """Synthetic photographs of a calibration board through ``camera``."""
    from companion.sitl.world.calibration import BoardRenderer, random_board_poses

    poses = random_board_poses(camera, spec, views, seed)
    return BoardRenderer(camera).render(spec, poses, seed)


def laser_frames(
    cfg: Config, frames: int, seed: int, tilt: tuple[int, float] | None
) -> list[LaserFrame]:
    """Synthetic laser-check frames of the config's vehicle, one sensor's mount pitched by
    ``tilt`` = (sensor id, degrees) on the simulated vehicle."""
    from companion.sitl.world.calibration import laser_check_frames, tilt_sensor

    hardware = cfg.rangefinders if tilt is None else tilt_sensor(cfg.rangefinders, *tilt)
    return laser_check_frames(cfg, frames, seed, hardware)


# ------------------------------------------------------------------------------ commands
def cmd_sitl_record(args: argparse.Namespace) -> int:
    """Record a SITL dataset."""
    from companion.sitl.world.dataset import record

    out = record(
        load(args),
        args.out,
        image_format=args.image_format,
        overwrite=args.overwrite,
        progress=not args.no_progress,
    )
    print(out)
    return EXIT_OK


def cmd_sitl_sheet(args: argparse.Namespace) -> int:
    """Write a PNG contact sheet of a dataset and print its path."""
    from companion.sitl.world.dataset import contact_sheet

    print(contact_sheet(open_dataset(args.dataset), args.out))
    return EXIT_OK


def cmd_sitl_run(args: argparse.Namespace) -> int:
    """The PX4-like SITL autopilot with its camera stream (sitl/stub/autopilot.py)."""
    from companion.sitl.stub.autopilot import SimAutopilot
    from companion.sitl.stub.faults import Fault
    from companion.sitl.stub.options import AutopilotOptions

    cfg = load(args)
    out = Path(args.out) if args.out else Path("out") / "sitl-run"
    faults = tuple(Fault.parse(f) for f in args.fault or ())
    key = load_key(args.signing_key, "--signing-key") if args.signing_key else b""
    opts = AutopilotOptions(
        prerender=args.prerender, faults=faults, signing_key=key, time_scale=args.time_scale
    )
    stub = SimAutopilot(cfg, opts)
    for f in faults:
        print(f"fault: {f.kind} at {f.start_s:g} s for {f.duration_s:g} s", flush=True)
    o = stub.opts
    print(
        f"SITL autopilot: {cfg.sitl.terrain}/{cfg.sitl.trajectory} {cfg.sitl.seconds:g} s, "
        f"listening on 127.0.0.1:{o.listen_port}, sending to "
        f"127.0.0.1:{o.companion_port}, camera on tcp 127.0.0.1:{o.camera_port}; "
        f"ground station (`companion px4 check --url udpin://127.0.0.1:{o.gcs_port}`) "
        f"from udp {o.gcs_listen_port} to {o.gcs_port}"
        + (f"; slow motion: {o.time_scale:g} flight s per s" if o.time_scale != 1.0 else ""),
        flush=True,
    )
    if args.prerender:
        print("rendering every camera frame before the flight (about a minute)...", flush=True)
    exit_on_sigterm()
    report = asyncio.run(stub.run(out))
    print(json.dumps(report, indent=2))
    print(f"report, received.csv and plot in {out}")
    return EXIT_OK


def cmd_sitl_px4(args: argparse.Namespace) -> int:
    """Fly the real PX4 SITL (SIH) on our estimate (sitl/loops/px4_flight.py)."""
    # by name, as before the split: sitl/loops/px4_flight.py and px4_results.py are not strict-mypy
    # clean, and a plain import would have mypy check them with companion/
    flight = importlib.import_module("companion.sitl.loops.px4_flight")
    return int(flight.cli_main(args))


def cmd_sitl_ardupilot(args: argparse.Namespace) -> int:
    """Fly the real ArduCopter SITL on our estimate (sitl/loops/ardupilot_flight.py)."""
    flight = importlib.import_module(
        "companion.sitl.loops.ardupilot_flight"
    )  # by name, as sitl px4
    return int(flight.cli_main(args))


def cmd_demo(args: argparse.Namespace) -> int:
    """SITL autopilot + service together on the SITL default; prints what the autopilot saw."""
    load(args)  # a bad config stops here (exit 2), before any process is started
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
    extra += ["--time-scale", str(args.time_scale)]
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
    print(_demo_summary(rep, svc))
    print(f"plots and logs: {out / 'autopilot' / 'autopilot.png'}, {out}")
    return EXIT_OK


def _demo_summary(rep: dict[str, Any], svc: dict[str, Any]) -> str:
    """What the autopilot saw (its report.json) and what the service did (service.json)."""
    return "\n".join(
        [
            f"received by the autopilot: {rep['received']} {rep['message']} at "
            f"{rep['received_rate_hz']:.1f} Hz",
            f"end-to-end latency (exposure -> autopilot): p50 {rep['latency_ms_p50']:.1f} ms, "
            f"p99 {rep['latency_ms_p99']:.1f} ms",
            f"metric ATE seen by the autopilot (SE3, its clock): {rep['ate_m']:.3f} m = "
            f"{rep['ate_pct']:.2f} % of {rep['path_m']:.0f} m; "
            f"scale error {rep['scale_error_pct']:+.2f} %",
            f"time sync: conversion error max {rep['timesync_error_ms_max']:.3f} ms; TIMESYNC "
            f"round trip p99 {rep.get('timesync_rtt_ms_p99', float('nan')):.2f} ms",
            f"service: {svc['frames_in']} frames, {svc['frames_dropped']} dropped, "
            f"capture-to-send p50 {svc['latency_ms_p50']:.1f} ms, "
            f"p99 {svc['latency_ms_p99']:.1f} ms",
        ]
    )


# ------------------------------------------------------------------------------ parsers
def add_sitl(sub: Any) -> None:
    """``companion sitl record | run | px4 | sheet``."""
    p_sitl = sub.add_parser("sitl", help="the simulator")
    sitl_sub = p_sitl.add_subparsers(dest="sitl_command", required=True)
    p_rec = sitl_sub.add_parser("record", help="record a dataset")
    add_sitl_flags(p_rec)
    p_rec.add_argument("--out", type=Path, required=True, help="output folder")
    p_rec.add_argument(
        "--image-format", choices=["jpg", "png"], default="jpg", help="frame files (default jpg)"
    )
    p_rec.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    p_rec.add_argument("--no-progress", action="store_true", help="no progress bar")
    p_rec.set_defaults(func=cmd_sitl_record)
    p_srun = sitl_sub.add_parser("run", help="the PX4-like SITL autopilot with its camera")
    add_sitl_flags(p_srun)
    p_srun.add_argument("--out", type=Path, help="report folder (default out/sitl-run)")
    p_srun.add_argument(
        "--prerender", action="store_true", help="render every frame before the flight"
    )
    p_srun.add_argument(
        "--fault",
        action="append",
        metavar="KIND@START+DURATION",
        help="inject a fault (repeatable): camera_freeze, camera_black, camera_saturated, "
        "camera_unplug, link_silence, link_port_change, autopilot_reboot (sitl/stub/faults.py)",
    )
    p_srun.add_argument(
        "--signing-key", help="sign with this 32-byte key file and refuse unsigned frames"
    )
    add_time_scale(p_srun)
    p_srun.set_defaults(func=cmd_sitl_run)
    p_px4 = sitl_sub.add_parser("px4", help="fly the real PX4 SITL (SIH) on our estimate")
    p_px4.add_argument("--px4", help="PX4 SITL launcher (else $PX4_SITL, ../shared/px4-sitl)")
    add_mission_and_seed(p_px4, "what PX4 flies (default square)")
    p_px4.add_argument("--instance", type=int, default=0, help="PX4 instance (ports shift by it)")
    p_px4.add_argument("--config", type=Path, help="default: config/px4_sitl.toml")
    p_px4.add_argument("--no-configure", action="store_true", help="skip `companion px4 configure`")
    p_px4.add_argument(
        "--air-start",
        action="store_true",
        help="arm in Altitude mode, climb on PX4's rangefinder and start the companion in the "
        "air (the take-off before the ground start; default: the companion starts on the "
        "ground and PX4 arms in Position mode)",
    )
    p_px4.add_argument("--out", type=Path, required=True, help="output folder")
    p_px4.set_defaults(func=cmd_sitl_px4)
    p_ap = sitl_sub.add_parser("ardupilot", help="fly the real ArduCopter SITL on our estimate")
    p_ap.add_argument(
        "--ardupilot",
        help="ArduPilot SITL launcher (else $ARDUPILOT_SITL, ../shared/ardupilot-sitl)",
    )
    add_mission_and_seed(p_ap, "what ArduCopter flies in GUIDED (default square)")
    p_ap.add_argument(
        "--heading",
        choices=["compass", "extnav"],
        default="compass",
        help="EKF3's heading: the compass with the site's declination (default; EKF3's north "
        "is true north) or ours alone (EKF3's north is the vehicle's first heading)",
    )
    p_ap.add_argument(
        "--instance", type=int, default=0, help="ArduPilot instance (TCP ports + 10 x N)"
    )
    p_ap.add_argument("--config", type=Path, help="default: config/px4_sitl.toml")
    p_ap.add_argument(
        "--no-configure", action="store_true", help="skip `companion autopilot configure`"
    )
    p_ap.add_argument("--out", type=Path, required=True, help="output folder")
    p_ap.set_defaults(func=cmd_sitl_ardupilot)
    p_sheet = sitl_sub.add_parser("sheet", help="write a PNG contact sheet of a dataset")
    p_sheet.add_argument("dataset", type=Path, help="dataset folder")
    p_sheet.add_argument("--out", type=Path, help="PNG file (default: in the dataset folder)")
    p_sheet.set_defaults(func=cmd_sitl_sheet)


def add_mission_and_seed(p: Any, mission_help: str) -> None:
    """``--mission`` (square | lawnmower | hover, and the GPS missions gps-denied-zone |
    gps-appears | gps-hover: sitl/loops/gps_missions.py) and ``--seed``, as both closed loops
    take them (sitl/loops/loop_flight.py, options_from_args)."""
    p.add_argument(
        "--mission",
        choices=["square", "lawnmower", "hover", "gps-denied-zone", "gps-appears", "gps-hover"],
        default="square",
        help=mission_help,
    )
    p.add_argument("--seed", type=int, default=1, help="world and sensor noise seed")


def time_scale(text: str) -> float:
    """--time-scale: a number in (0, 1] (argparse exits 2 naming the option otherwise)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text}: must be in (0, 1]")
    return value


def add_time_scale(p: Any) -> None:
    """The SITL flight's --time-scale (sitl/stub/autopilot.py, AutopilotOptions.time_scale)."""
    p.add_argument(
        "--time-scale",
        type=time_scale,
        default=1.0,
        metavar="S",
        help="flight seconds per second (default 1; 0.5: a slow-motion flight, the camera at "
        "half its rate, for a machine that cannot keep up in real time)",
    )


def add_demo(sub: Any) -> None:
    """``companion demo``."""
    p_demo = sub.add_parser("demo", help="SITL autopilot + service together, with a summary")
    add_sitl_flags(p_demo)
    p_demo.add_argument("--out", type=Path, help="output folder (default out/demo)")
    p_demo.add_argument(
        "--prerender",
        action="store_true",
        help="render the camera before the flight (latency without the renderer's CPU load)",
    )
    add_time_scale(p_demo)
    p_demo.set_defaults(func=cmd_demo)
