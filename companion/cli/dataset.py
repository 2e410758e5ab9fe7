"""``companion dataset ...``: real sequences into our dataset format (docs/dataset.md,
"Importing real sequences").

    companion dataset import FORMAT SRC --out DIR [--config FILE] [--frames A:B] [--seed N]
                             [--camera fr1|fr2|fr3] [--sequence NN] [--image-format keep|png|jpg]
                             [--jpg-quality Q]
    companion dataset rebuild NAME... | --all --snapshots DIR --out DIR [--manifest FILE]
    companion dataset convert SRC DST
    companion dataset truth-check DIR --floor-z Z [--frames A:B] [--gap N] [--step N]
                                  [--offsets-ms MS,...] [--fit-lens]

FORMAT: tum-rgbd (also its keyframe variant), eth3d, 7scenes, kitti; rislab (the RIS lab's
downward flight: images60fps/ and mocap_data.mat; ``--focal-px``, ``--k1``: its lens). The
distance sensors are synthesised from the depth images: the ``[[rangefinders]]`` of
``--config`` (mounts in the camera frame: the body is the camera), else four beams near the
optical axis. ``rebuild``
reads config/real_sequences.toml, extracts each sequence from its git snapshot, checks its
checksums and imports it into DIR/NAME. ``convert`` turns a flight recording folder into one
MCAP file (DST ending in ``.mcap``) or an MCAP recording into a folder, losslessly (the replay
is the same, bit for bit). ``truth-check`` scores how much of the floor's image motion a
downward dataset's truth explains (a wrong mount, clock or lens shows). Exit codes: 0 done,
2 bad input (a malformed list line, a checksum that differs, a bad config: the message names
the file, line or key).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from companion.config import Config, RangefinderConfig, from_dict
from companion.drivers.dataset.import_manifest import IMPORTERS, read_manifest, rebuild
from companion.drivers.dataset.import_sources import TUM_CAMERAS, read_source
from companion.drivers.dataset.import_write import (
    DEFAULT_BEAMS,
    IMAGE_FORMATS,
    ImportSummary,
    import_sequence,
    select_frames,
)
from companion.drivers.safe_files import SafeFolder
from companion.errors import DatasetError
from companion.toml_files import read_config_toml

DEFAULT_MANIFEST = Path("config/real_sequences.toml")


def rangefinders_of(config_path: Path | None) -> tuple[RangefinderConfig, ...]:
    """The ``[[rangefinders]]`` of a config file (mounts in the camera frame), or the four
    default beams when there is no file or it declares none."""
    if config_path is None:
        return DEFAULT_BEAMS
    data = read_config_toml(config_path)
    if "rangefinders" not in data:
        return DEFAULT_BEAMS
    return from_dict(Config, data).rangefinders


def _summary_line(out: Path, s: ImportSummary) -> str:
    dropped = ", ".join(f"{k} {v}" for k, v in s.dropped.items() if v) or "nothing"
    return (
        f"{out}: {s.frames} frames, {s.readings} synthesised readings, path "
        f"{s.path_length_m:.2f} m; left out: {dropped}"
    )


def cmd_import(args: argparse.Namespace) -> int:
    """Import one folder."""
    if args.format == "rislab":
        return _import_rislab(args)
    folder = SafeFolder(args.src)
    seq = read_source(args.format, folder, args.camera, args.sequence)
    seq = select_frames(seq, args.frames)
    summary = import_sequence(
        seq,
        folder,
        args.out,
        rangefinders_of(args.config),
        seed=args.seed,
        image_format=args.image_format,
        jpg_quality=args.jpg_quality,
        source_meta={"source_path": str(args.src)},
    )
    print(_summary_line(args.out, summary))
    return 0


def _import_rislab(args: argparse.Namespace) -> int:
    """The RIS lab downward flight (drivers/dataset/rislab.py): sensors synthesised over its
    floor (``--config``'s [[rangefinders]] as mounted on the body, else four on the arms)."""
    from companion.config import load_config
    from companion.drivers.dataset.rislab import RISLAB_BEAMS, import_rislab

    first, _, last = args.frames.partition(":")
    beams = rangefinders_of(args.config) if args.config is not None else RISLAB_BEAMS
    summary = import_rislab(
        args.src,
        args.out,
        load_config(),
        beams,
        focal_px=args.focal_px,
        dist=(args.k1, args.k2, 0.0, 0.0, 0.0),
        frames=(int(first), int(last)) if last else None,
        seed=args.seed,
    )
    print(_summary_line(args.out, summary))
    return 0


def cmd_rebuild(args: argparse.Namespace) -> int:
    """Rebuild manifest entries from their snapshots."""
    entries = read_manifest(args.manifest)
    by_name = {e.name: e for e in entries}
    if args.all == bool(args.names):
        raise DatasetError(f"rebuild: NAME... or --all (the manifest has {sorted(by_name)})")
    names = [e.name for e in entries if e.importer in IMPORTERS] if args.all else args.names
    for name in names:
        if name not in by_name:
            raise DatasetError(f"rebuild: {name!r} is not in {args.manifest} ({sorted(by_name)})")
        out = args.out / name
        print(_summary_line(out, rebuild(by_name[name], args.snapshots, out)))
    return 0


def cmd_truth_check(args: argparse.Namespace) -> int:
    """The floor's flow against the truth (drivers/dataset/truth_check.py)."""
    from companion.drivers.dataset import open_dataset
    from companion.drivers.dataset.truth_check import check_truth, report_lines

    first, _, last = args.frames.partition(":")
    try:
        offsets = tuple(1e-3 * float(v) for v in args.offsets_ms.split(","))
        frames = (int(first), int(last)) if last else None
    except ValueError:
        raise DatasetError(
            f"--offsets-ms {args.offsets_ms!r} / --frames {args.frames!r}: numbers, as 0,33 / A:B"
        ) from None
    if args.gap < 1 or args.step < 1:
        raise DatasetError("--gap and --step: at least 1")
    check = check_truth(
        open_dataset(args.dataset),
        args.floor_z,
        frames,
        args.gap,
        args.step,
        offsets,
        args.fit_lens,
    )
    print("\n".join(report_lines(check)))
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    """A flight recording from a folder into an MCAP file, or back."""
    from companion.drivers.dataset import open_dataset
    from companion.drivers.dataset.convert import convert_recording

    ds = open_dataset(args.src)
    try:
        done = convert_recording(ds, args.dst)
    except FileExistsError:
        raise DatasetError(f"{args.dst} exists: convert writes a new file or folder") from None
    print(
        f"{args.dst}: {done.frames} frames, {done.samples} samples, {done.published} "
        f"published poses{'' if ds.complete else ' (the source was not closed)'}"
    )
    return 0


def add_parser(sub: Any) -> None:
    """``companion dataset``."""
    p = sub.add_parser("dataset", help="import real sequences into our dataset format")
    dsub = p.add_subparsers(
        dest="dataset_command", required=True, metavar="{import,rebuild,convert,truth-check}"
    )
    pi = dsub.add_parser("import", help="a real-sequence folder into our format")
    pi.add_argument("format", choices=IMPORTERS, help="the source's format")
    pi.add_argument("src", type=Path, help="the source folder")
    pi.add_argument("--out", type=Path, required=True, help="a new (or empty) folder")
    pi.add_argument(
        "--config", type=Path, help="[[rangefinders]] to synthesise (mounts in the camera frame)"
    )
    pi.add_argument("--frames", default="", help="A:B: only these kept frames (a slice)")
    pi.add_argument("--seed", type=int, default=1, help="seed of the range noise")
    pi.add_argument(
        "--camera",
        choices=sorted(TUM_CAMERAS),
        default="fr1",
        help="tum-rgbd: which published TUM calibration (fr1, fr2, fr3)",
    )
    pi.add_argument("--sequence", default="", help="kitti: the sequence NN")
    pi.add_argument(
        "--image-format",
        choices=IMAGE_FORMATS,
        default="keep",
        help="keep: copy the source's PNG/JPEG bytes; png or jpg: re-encode",
    )
    pi.add_argument(
        "--jpg-quality", type=int, default=95, help="--image-format jpg: quality 1..100"
    )
    pi.add_argument("--focal-px", type=float, default=235.5, help="rislab: focal length [px]")
    pi.add_argument("--k1", type=float, default=0.0, help="rislab: radial distortion k1")
    pi.add_argument("--k2", type=float, default=0.0, help="rislab: radial distortion k2")
    pi.set_defaults(func=cmd_import)
    pr = dsub.add_parser("rebuild", help="manifest sequences from their git snapshots")
    pr.add_argument("names", nargs="*", metavar="NAME", help="manifest entries to rebuild")
    pr.add_argument("--all", action="store_true", help="every entry whose importer is built")
    pr.add_argument("--snapshots", type=Path, required=True, help="folder of owner+name/ snapshots")
    pr.add_argument("--out", type=Path, required=True, help="write DIR/NAME per sequence")
    pr.add_argument(
        "--manifest",
        type=Path,
        default=DEFAULT_MANIFEST,
        help=f"the manifest (default {DEFAULT_MANIFEST})",
    )
    pr.set_defaults(func=cmd_rebuild)
    pc = dsub.add_parser("convert", help="a flight recording: folder <-> MCAP file, lossless")
    pc.add_argument("src", type=Path, help="a recording: a folder, or an .mcap file")
    pc.add_argument("dst", type=Path, help="a new .mcap file, or a new folder")
    pc.set_defaults(func=cmd_convert)
    pt = dsub.add_parser(
        "truth-check", help="does a downward dataset's truth move like its images (floor flow)"
    )
    pt.add_argument("dataset", type=Path, help="a dataset folder with groundtruth.txt")
    pt.add_argument(
        "--floor-z", type=float, required=True, help="the floor: the plane z = Z [m] of its world"
    )
    pt.add_argument("--frames", default="", help="A:B: frame indices to use (default all)")
    pt.add_argument("--gap", type=int, default=3, help="frames between the two of a pair")
    pt.add_argument("--step", type=int, default=5, help="a pair every STEP frames")
    pt.add_argument(
        "--offsets-ms",
        default="0",
        help="comma-separated offsets of the truth against the stamps to score [ms]",
    )
    pt.add_argument(
        "--fit-lens", action="store_true", help="also fit focal, k1, k2 at the best offset"
    )
    pt.set_defaults(func=cmd_truth_check)
