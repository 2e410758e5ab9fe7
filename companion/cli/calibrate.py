"""``companion calibrate ...``: camera intrinsics from board photographs, and a check of the
distance sensors' mounts against photographs with the laser dots visible.

    companion calibrate board --board SPEC --out board.png [--dpi 300]
    companion calibrate intrinsics --images DIR --board SPEC [--out DIR]
    companion calibrate lasers --config CFG --images DIR [--ranges FILE] [--out DIR]
    companion calibrate sim-board --board SPEC --out DIR      (synthetic photographs)
    companion calibrate sim-lasers --out DIR [--tilt-sensor ID:DEG]

Exit codes: 0 done (``lasers``: every sensor OK), 1 ``lasers`` flagged a sensor, 2 bad input
(missing folder, no board found, too few views, a bad ranges file or config).
The options of :class:`IntrinsicsOptions` and :class:`LaserCheckOptions` become flags by
walking their fields (``--max-offset-px``), so their defaults and help live in one place.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2

from companion.calibration.figures import coverage_image, intrinsics_summary, laser_overlay
from companion.calibration.files import (
    list_images,
    read_image,
    read_laser_frames,
    write_laser_frames,
)
from companion.calibration_maths.board import _SPEC_HELP, BoardDetector, BoardSpec, board_image
from companion.calibration_maths.intrinsics import IntrinsicsOptions, calibrate_intrinsics
from companion.calibration_maths.lasers import LaserCheckOptions, Verdict, check_lasers
from companion.cli import sim
from companion.cli.common import add_option_flags, options
from companion.config import load_config
from companion.errors import CalibrationError, NotEnoughViewsError

EXIT_OK, EXIT_FLAGGED, EXIT_INPUT = 0, 1, 2
Command = Callable[[argparse.Namespace], int]


def _input_errors(func: Command) -> Command:
    """CalibrationError -> its message on stderr and exit code 2 (bad input, like ConfigError)."""

    @functools.wraps(func)
    def run(args: argparse.Namespace) -> int:
        try:
            return func(args)
        except CalibrationError as e:
            print(f"companion: calibrate: {e}", file=sys.stderr)
            return EXIT_INPUT
        except (OSError, cv2.error) as e:  # an unwritable --out, an image format OpenCV lacks
            print(f"companion: calibrate: cannot write the output: {e}", file=sys.stderr)
            return EXIT_INPUT

    return run


def _write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=2) + "\n")


# ------------------------------------------------------------------------------ board
@_input_errors
def cmd_board(args: argparse.Namespace) -> int:
    """Write a printable board image."""
    spec = BoardSpec.parse(args.board)
    img = board_image(spec, args.dpi / 0.0254, margin_squares=1.0)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(args.out), img.image):
        raise CalibrationError(f"{args.out}: cannot write (use a .png name)")
    h, w = img.image.shape
    sq_mm = 1000 * spec.square_m * img.px_per_m / (args.dpi / 0.0254)
    print(
        f"{args.out}: {spec.text()}, {w}x{h} px = {25.4 * w / args.dpi:.0f} x "
        f"{25.4 * h / args.dpi:.0f} mm at {args.dpi} dpi; squares {sq_mm:.2f} mm.\n"
        "Print at 100 % (no 'fit to page'), glue it on something flat and rigid, check a square "
        "with a ruler and give the measured size to `calibrate intrinsics`."
    )
    return EXIT_OK


# ------------------------------------------------------------------------------ intrinsics
@_input_errors
def cmd_intrinsics(args: argparse.Namespace) -> int:
    """Calibrate the camera from photographs of a board."""
    spec = BoardSpec.parse(args.board)
    opts = options(args, IntrinsicsOptions)
    paths = list_images(args.images)
    detector = BoardDetector(spec)
    views = []
    size: tuple[int, int] | None = None
    missed = []
    for p in paths:
        img = read_image(p, size)
        size = (img.shape[1], img.shape[0])
        view = detector.detect(img, p.name)
        if view is None:
            missed.append(p.name)
        else:
            views.append(view)
    assert size is not None
    if not views:
        what = "inner corners" if spec.kind == "chessboard" else "squares"
        raise CalibrationError(
            f"{args.images}: the board {spec.text()} was not found in any of the {len(paths)} "
            f"image(s): check COLSxROWS (counted in {what}), that the whole board is in view "
            "(chessboard), sharp and evenly lit"
        )
    try:
        result = calibrate_intrinsics(views, size, opts)
    except NotEnoughViewsError as e:
        raise NotEnoughViewsError(
            f"{e} (the board was found in {len(views)} of {len(paths)} images)"
        ) from None
    out = args.out or Path("out") / "calibration" / "intrinsics"
    out.mkdir(parents=True, exist_ok=True)
    (out / "camera.toml").write_text(result.camera_toml())
    report = {
        "board": spec.text(),
        "images": len(paths),
        "images_without_board": missed,
        "opencv": cv2.__version__,
        **result.report(),
    }
    _write_json(out / "intrinsics.json", report)
    used = {v.name for v in views} - {n for n, _ in result.dropped}
    cv2.imwrite(
        str(out / "coverage.png"), coverage_image(result, [v for v in views if v.name in used])
    )
    print(intrinsics_summary(result, len(views), len(paths), spec))
    print()
    print(result.camera_toml(), end="")
    print(f"\nwritten: {out / 'camera.toml'}, {out / 'intrinsics.json'}, {out / 'coverage.png'}")
    return EXIT_OK


# ------------------------------------------------------------------------------ lasers
@_input_errors
def cmd_lasers(args: argparse.Namespace) -> int:
    """Check the rangefinder mounts against images with the laser dots visible."""
    cfg = load_config(args.config)
    opts = options(args, LaserCheckOptions)
    frames = read_laser_frames(args.images, args.ranges)
    h, w = frames[0].image_bgr.shape[:2]
    if (w, h) != (cfg.camera.width, cfg.camera.height):
        raise CalibrationError(
            f"{args.images}: images are {w}x{h} px but [camera] in {args.config} is "
            f"{cfg.camera.width}x{cfg.camera.height}: the intrinsics are for another mode"
        )
    report = check_lasers(
        cfg.camera.model(),
        cfg.camera.T_body_cam(),
        [rf.spec() for rf in cfg.rangefinders],
        frames,
        opts,
    )
    out = args.out or Path("out") / "calibration" / "lasers"
    (out / "overlays").mkdir(parents=True, exist_ok=True)
    _write_json(out / "lasers.json", {"config": str(args.config), **report.report()})
    for f in frames:
        cv2.imwrite(str(out / "overlays" / f"{Path(f.name).stem}.png"), laser_overlay(f, report))
    print(report.table())
    mounts = {rf.sensor_id: rf.mount for rf in cfg.rangefinders}
    for s in report.sensors:
        if s.verdict is Verdict.CHECK_MOUNT and s.suggested_rpy_deg is not None:
            rpy = ", ".join(f"{a:.3f}" for a in s.suggested_rpy_deg)
            print(
                f"sensor {s.sensor_id}: the dots say its [rangefinders.mount] rpy_deg = [{rpy}] "
                f"(configured {list(mounts[s.sensor_id].rpy_deg)}), xyz_m kept; check the "
                "bracket before changing the config"
            )
    print(f"written: {out / 'lasers.json'}, {out / 'overlays'}/")
    return EXIT_OK if report.all_ok else EXIT_FLAGGED


# ------------------------------------------------------------------------------ simulated input
@_input_errors
def cmd_sim_board(args: argparse.Namespace) -> int:
    """Synthetic board photographs through the config's camera model (to try `intrinsics`)."""
    spec = BoardSpec.parse(args.board)
    camera = load_config(args.config).camera.model()
    images = sim.board_photos(camera, spec, args.views, args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    for k, img in enumerate(images):
        cv2.imwrite(str(args.out / f"board_{k:03d}.png"), img)
    c = camera
    print(
        f"{len(images)} views of {spec.text()} in {args.out}; truth fx {c.fx:g} fy {c.fy:g} "
        f"cx {c.cx:g} cy {c.cy:g} dist {[float(v) for v in c.dist_coeffs]}"
    )
    return EXIT_OK


def _tilt(text: str) -> tuple[int, float]:
    try:
        sid, deg = text.split(":")
        return int(sid), float(deg)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ID:DEG, got {text!r}") from None


@_input_errors
def cmd_sim_lasers(args: argparse.Namespace) -> int:
    """Synthetic laser-check frames (images + ranges.csv) from the SITL renderer."""
    cfg = load_config(args.config)
    frames = sim.laser_frames(cfg, args.frames, args.seed, args.tilt_sensor)
    path = write_laser_frames(args.out, frames)
    tilted = "" if args.tilt_sensor is None else f", sensor {args.tilt_sensor[0]} pitched by " \
        f"{args.tilt_sensor[1]:g} deg on the simulated vehicle"  # fmt: skip
    print(f"{len(frames)} frames and {path} in {args.out}{tilted}")
    return EXIT_OK


# ------------------------------------------------------------------------------ parser
def add_parser(sub: Any) -> None:
    """Add ``calibrate`` and its subcommands to the ``companion`` subparsers ``sub``."""
    p = sub.add_parser("calibrate", help="camera intrinsics; check the rangefinder mounts")
    cal = p.add_subparsers(dest="calibrate_command", required=True)

    p_board = cal.add_parser("board", help="write a printable calibration board (PNG)")
    p_board.add_argument("--board", required=True, help=_SPEC_HELP)
    p_board.add_argument("--out", type=Path, required=True, help="PNG file to write")
    p_board.add_argument("--dpi", type=int, default=300, help="printer resolution (default 300)")
    p_board.set_defaults(func=cmd_board)

    p_in = cal.add_parser("intrinsics", help="camera intrinsics from photographs of a board")
    p_in.add_argument("--images", type=Path, required=True, help="folder of board photographs")
    p_in.add_argument("--board", required=True, help=_SPEC_HELP)
    p_in.add_argument("--out", type=Path, help="report folder (default out/calibration/intrinsics)")
    add_option_flags(p_in, IntrinsicsOptions)
    p_in.set_defaults(func=cmd_intrinsics)

    p_las = cal.add_parser(
        "lasers", help="check the rangefinder mounts: laser dots vs where the model puts them"
    )
    p_las.add_argument("--config", type=Path, required=True, help="the config to check")
    p_las.add_argument(
        "--images", type=Path, required=True, help="folder of images with the laser dots visible"
    )
    p_las.add_argument(
        "--ranges", type=Path, help="CSV image,sensor_id,range_m (default IMAGES/ranges.csv)"
    )
    p_las.add_argument("--out", type=Path, help="report folder (default out/calibration/lasers)")
    add_option_flags(p_las, LaserCheckOptions)
    p_las.set_defaults(func=cmd_lasers)

    p_sb = cal.add_parser("sim-board", help="synthetic board photographs (SITL camera model)")
    p_sb.add_argument("--board", required=True, help=_SPEC_HELP)
    p_sb.add_argument("--out", type=Path, required=True, help="folder to write")
    p_sb.add_argument("--config", type=Path, help="camera from this config (default built-in)")
    p_sb.add_argument("--views", type=int, default=15, help="number of views (default 15)")
    p_sb.add_argument(
        "--seed", type=int, default=1, help="seed of the board poses and image noise (default 1)"
    )
    p_sb.set_defaults(func=cmd_sim_board)

    p_sl = cal.add_parser("sim-lasers", help="synthetic laser-check frames over a flat floor")
    p_sl.add_argument("--out", type=Path, required=True, help="folder to write")
    p_sl.add_argument("--config", type=Path, help="vehicle config (default built-in)")
    p_sl.add_argument("--frames", type=int, default=12, help="number of frames (default 12)")
    p_sl.add_argument(
        "--seed", type=int, default=1, help="seed of the simulated frames (default 1)"
    )
    p_sl.add_argument(
        "--tilt-sensor",
        type=_tilt,
        metavar="ID:DEG",
        help="pitch this sensor by DEG on the simulated vehicle (a mount the config gets wrong)",
    )
    p_sl.set_defaults(func=cmd_sim_lasers)
