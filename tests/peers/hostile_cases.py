"""The hostile and damaged dataset cases of tests/e2e/test_hostile_inputs.py: each a named edit
of a small valid dataset (tests/peers/hostile_datasets.py) and what `companion eval` must say
of it (exit 2 and the words of its one line, or the bad rows it counts)."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from peers.hostile_datasets import (
    HEIGHT,
    WIDTH,
    Files,
    edit_text,
    make_fifo,
    png_bomb,
    png_of,
    replace_field,
)

IMG0 = "images/000000.png"
EUROC_CAM = "mav0/cam0"
EUROC_FIRST = "mav0/cam0/data/1000000000.png"


@dataclass(frozen=True)
class Case:
    """A hostile dataset: ``edit`` changes the files (bytes), ``place`` the folder on disk
    (links, FIFOs; given the folder and a folder outside it holding valid images). ``says``:
    what the one-line error names (exit 2), or with ``ok`` the file whose bad rows the
    completed eval counts ("" when none is expected)."""

    name: str
    says: str
    edit: Callable[[Files], None] = lambda files: None
    place: Callable[[Path, Path], None] = lambda folder, outside: None
    ok: bool = False
    euroc: bool = False


def _frames(value: str, column: str = "time_us", row: int = 3) -> Callable[[Files], None]:
    return lambda f: replace_field(f, "frames.csv", row, column, value)


def _field(name: str, column: str, value: str, row: int = 2) -> Callable[[Files], None]:
    return lambda f: replace_field(f, name, row, column, value)


def _text(name: str, edit: Callable[[str], str]) -> Callable[[Files], None]:
    return lambda f: edit_text(f, name, edit)


def cut_mid_row(text: str) -> str:
    """A TOML text cut inside a row, half-way through the file: just after the "=" of the
    first key = value row from the middle on (a cut at a line's end would leave a valid,
    shorter file, which is no damage a reader can see)."""
    at = text.find(" = ", len(text) // 2)
    return text[: at + 2] if at >= 0 else text[: len(text) // 2]


def _replace(name: str, old: str, new: str, count: int = -1) -> Callable[[Files], None]:
    """The text file ``name`` with ``old`` replaced by ``new`` (the first ``count`` times)."""
    return _text(name, lambda t: t.replace(old, new, count))


def _set(name: str, data: bytes) -> Callable[[Files], None]:
    return lambda f: f.__setitem__(name, data)


def _drop(name: str) -> Callable[[Files], None]:
    return lambda f: f.pop(name)


def _symlink(name: str, target: Callable[[Path], Path]) -> Callable[[Path, Path], None]:
    def place(folder: Path, outside: Path) -> None:
        path = folder / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()
        path.symlink_to(target(outside))

    return place


def _fifo(name: str) -> Callable[[Path, Path], None]:
    return lambda folder, outside: make_fifo(folder / name)


def _swap_rows(name: str, a: int, b: int) -> Callable[[Files], None]:
    def edit(files: Files) -> None:
        lines = files[name].decode().split("\n")
        lines[a], lines[b] = lines[b], lines[a]
        files[name] = "\n".join(lines).encode()

    return edit


def _dup_row(name: str, row: int) -> Callable[[Files], None]:
    def edit(files: Files) -> None:
        lines = files[name].decode().split("\n")
        lines.insert(row, lines[row])
        files[name] = "\n".join(lines).encode()

    return edit


DEEP = "x = " + "[" * 30_000 + "]" * 30_000 + "\n"
DEEP_TABLE = "[" + ".".join(["a"] * 30_000) + "]\nx = 1\n"
HUGE = "9" * 5_000
CSVS = ("frames.csv", "ranges.csv", "attitude.csv", "imu.csv", "published.csv")
TOMLS = ("meta.toml", "calibration.toml", "config.toml")

CASES = [
    # outside the folder: refused, nothing there opened
    Case("dotdot-path", "frames.csv row 4, filename", _frames("../../outside/x.png", "filename")),
    Case("absolute-path", "frames.csv row 4, filename"),  # the path: filled in by _build
    Case("etc-shadow", "frames.csv row 4, filename", _frames("../../../../etc/shadow", "filename")),
    Case("dev-zero", "absolute file name", _frames("/dev/zero", "filename")),
    Case("symlink-image-out", "resolves outside", place=_symlink(IMG0, lambda o: o / "x.png")),
    Case("symlink-images-dir-out", "resolves outside", place=_symlink("images", lambda o: o)),
    Case(
        "symlink-images-etc", "resolves outside", place=_symlink("images", lambda o: Path("/etc"))
    ),
    Case(
        "symlink-meta-out",
        "resolves outside",
        place=_symlink("meta.toml", lambda o: o / "meta.toml"),
    ),
    # not regular files: refused at once
    Case("fifo-image", "is a FIFO", place=_fifo(IMG0)),
    Case("fifo-meta", "is a FIFO", place=_fifo("meta.toml")),
    Case("fifo-ranges", "is a FIFO", place=_fifo("ranges.csv")),
    Case(
        "directory-image",
        "is a directory",
        place=lambda d, o: (d / IMG0).unlink() or (d / IMG0).mkdir(),
    ),
    # TOML
    Case(
        "deep-meta", "meta.toml: tables or arrays nested deeper", _set("meta.toml", DEEP.encode())
    ),
    Case(
        "deep-table-calibration",
        "calibration.toml: tables or arrays nested deeper",
        _set("calibration.toml", DEEP_TABLE.encode()),
    ),
    Case(
        "deep-config",
        "config.toml: tables or arrays nested deeper",
        _set("config.toml", DEEP.encode()),
    ),
    Case("meta-latin1", "meta.toml: not UTF-8", _set("meta.toml", b'format = "caf\xe9"\n')),
    Case("meta-nul", "meta.toml: a NUL byte", _text("meta.toml", lambda t: t + "\x00\n")),
    Case(
        "meta-huge-int",
        "meta.toml: not valid TOML",
        _text("meta.toml", lambda t: t + f"x = {HUGE}\n"),
    ),
    Case(
        "calibration-huge-int",
        "camera.width: integer out of range",
        _replace("calibration.toml", f"width = {WIDTH}", "width = " + "9" * 30),
    ),
    Case(
        "calibration-nan",
        "camera.fx: must be finite",
        _replace("calibration.toml", "fx = ", "fx = nan #"),
    ),
    Case(
        "calibration-lens-not-invertible",
        "bad calibration.toml/config.toml: camera.dist: the lens model",
        _replace("calibration.toml", "dist = [-0.12,", "dist = [-40.0,"),
    ),
    Case(
        "config-unknown-table",
        "config.toml: unexpected tables",
        _text("config.toml", lambda t: t + "\n[service]\nx = 1\n"),
    ),
    Case("sitl-not-a-table", "bad calibration", _text("meta.toml", lambda t: "sitl = 3\n" + t)),
    # each TOML and CSV file missing, empty, truncated mid-row
    *[Case(f"missing-{n}", n, _drop(n)) for n in ("meta.toml", "calibration.toml")],
    Case("missing-config", "", _drop("config.toml"), ok=True),
    *[Case(f"empty-{n}", "", _set(n, b""), ok=n == "config.toml") for n in TOMLS],
    *[Case(f"truncated-{n}", n, _text(n, cut_mid_row)) for n in TOMLS],
    Case("missing-frames", "frames.csv: file not found", _drop("frames.csv")),
    *[Case(f"missing-{n}", "", _drop(n), ok=True) for n in CSVS[1:]],
    Case("empty-frames", "frames.csv: empty", _set("frames.csv", b"")),
    *[Case(f"empty-{n}", "", _set(n, b""), ok=True) for n in CSVS[1:]],
    *[Case(f"torn-{n}", "", _text(n, lambda t: t[:-12]), ok=True) for n in CSVS],
    # frames.csv rows: exit 2 naming the row and the field
    Case(
        "frames-missing-column",
        "missing column 'seq'",
        _replace("frames.csv", "time_us,seq,", "time_us,sequence,", 1),
    ),
    Case("frames-text-time", "frames.csv row 4, time_us: not an integer", _frames("soon")),
    Case("frames-nan-time", "frames.csv row 4, time_us: not an integer", _frames("nan")),
    Case("frames-inf-seq", "frames.csv row 4, seq: not an integer", _frames("inf", "seq")),
    Case("frames-5000-digits", "frames.csv row 4, time_us: not an integer: '99999", _frames(HUGE)),
    Case("frames-200kB-field", "frames.csv row 4", _frames("x" * 200_000, "filename")),
    Case("frames-duplicated-time", "frames.csv row 4, time_us", _dup_row("frames.csv", 2)),
    Case("frames-decreasing-time", "frames.csv row", _swap_rows("frames.csv", 2, 3)),
    Case("frames-extra-column", "", _replace("frames.csv", "\n", ",x\n"), ok=True),
    # samples: bad rows left out and counted, the eval completes
    Case("ranges-text", "ranges.csv", _field("ranges.csv", "distance_m", "far"), ok=True),
    Case("ranges-nan", "ranges.csv", _field("ranges.csv", "distance_m", "nan"), ok=True),
    Case(
        "ranges-5000-digit-fed",
        "ranges.csv",
        _field("ranges.csv", "fed_before_frame", HUGE),
        ok=True,
    ),
    Case("ranges-fed-decreases", "ranges.csv", _swap_rows("ranges.csv", 2, 5), ok=True),
    Case("ranges-extra-field", "ranges.csv", _field("ranges.csv", "time_us", "1,2"), ok=True),
    Case(
        "ranges-missing-column",
        "ranges.csv row 1 (header): missing column 'distance_m'",
        _replace("ranges.csv", "distance_m", "dist", 1),
    ),
    Case("ranges-duplicated", "", _dup_row("ranges.csv", 2), ok=True),
    Case("attitude-zero-quaternion", "attitude.csv", _field("attitude.csv", "qw", "0.0"), ok=True),
    Case("attitude-inf-rate", "attitude.csv", _field("attitude.csv", "wx_rad_s", "inf"), ok=True),
    Case("attitude-decreasing", "attitude.csv", _swap_rows("attitude.csv", 2, 4), ok=True),
    Case("imu-huge", "imu.csv", _field("imu.csv", "az_m_s2", "1e300"), ok=True),
    Case("published-junk", "published.csv", _field("published.csv", "x_m", "junk"), ok=True),
    Case("groundtruth-junk", "groundtruth.txt line 1", _set("groundtruth.txt", b"1 2 3\n")),
    # images
    Case(
        "image-other-size",
        "frame 0 (images/000000.png): PNG of 97 x 72 px",
        _set(IMG0, png_of(WIDTH + 1, HEIGHT)),
    ),
    Case("image-bomb-header", "PNG of 2048 x 2048 px", _set(IMG0, png_bomb(2048, 1))),
    Case("image-not-an-image", "not a PNG or JPEG", _set(IMG0, b"hello\n")),
    Case(
        "image-truncated",
        "frame 0 (images/000000.png): damaged PNG (no IEND",
        lambda f: f.__setitem__(IMG0, f[IMG0][:40]),
    ),
    Case("image-empty", "not a PNG or JPEG", _set(IMG0, b"")),
    # EuRoC
    Case(
        "euroc-no-intrinsics",
        "sensor.yaml: no 'intrinsics'",
        euroc=True,
        edit=_replace(f"{EUROC_CAM}/sensor.yaml", "intrinsics", "intr"),
    ),
    Case(
        "euroc-nan-intrinsics",
        "sensor.yaml, intrinsics[0]: not a finite number",
        euroc=True,
        edit=_replace(f"{EUROC_CAM}/sensor.yaml", "[80.0,", "[nan,"),
    ),
    Case(
        "euroc-text-time",
        f"{EUROC_CAM}/data.csv row 3, timestamp",
        euroc=True,
        edit=_replace(f"{EUROC_CAM}/data.csv", "1033333000,", "soon,", 1),
    ),
    Case(
        "euroc-dotdot",
        "'..' in file name",
        euroc=True,
        edit=_replace(f"{EUROC_CAM}/data.csv", ",1033333000.png", ",../x.png"),
    ),
    Case(
        "euroc-truth-junk",
        "state_groundtruth_estimate0/data.csv",
        euroc=True,
        ok=True,
        edit=_replace(
            "mav0/state_groundtruth_estimate0/data.csv", ",1.0,0.0,0.0,0.0\n", ",0,0,0,0\n", 1
        ),
    ),
    Case(
        "euroc-mav0-out",
        "resolves outside",
        euroc=True,
        place=_symlink("mav0", lambda o: o / "mav0"),
    ),
    Case(
        "euroc-other-size",
        "PNG of 97 x 72 px",
        euroc=True,
        edit=_set(EUROC_FIRST, png_of(WIDTH + 1, HEIGHT)),
    ),
]
