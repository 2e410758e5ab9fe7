"""A recording, dataset or config from anywhere never crashes, hangs, reads outside its folder or
exhausts the machine (the issue "Reliability round 3"): each hostile or damaged case ends in
`companion eval` exit 2 with one line naming the file, the row and the field, or in a completed
eval with the bad rows counted, and nothing outside the folder is opened."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import pytest
from peers.hostile_datasets import (
    HEIGHT,
    WIDTH,
    Files,
    edit_text,
    make_fifo,
    materialise,
    png_bomb,
    png_of,
    replace_field,
    set_png_size,
    snapshot,
    write_euroc,
    write_recording,
)

from companion.cli import main
from companion.drivers.dataset import open_dataset
from companion.drivers.safe_files import check_image_header, image_header
from companion.errors import DatasetError

REPO = Path(__file__).resolve().parents[2]
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
        _text("calibration.toml", lambda t: t.replace(f"width = {WIDTH}", "width = " + "9" * 30)),
    ),
    Case(
        "calibration-nan",
        "camera.fx: must be finite",
        _text("calibration.toml", lambda t: t.replace("fx = ", "fx = nan #")),
    ),
    Case(
        "calibration-lens-not-invertible",
        "calibration.toml [camera]: the camera model cannot be used: undistortion did not",
        _text("calibration.toml", lambda t: t.replace("dist = [-0.12,", "dist = [-40.0,")),
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
    *[Case(f"truncated-{n}", n, _text(n, lambda t: t[: len(t) // 2])) for n in TOMLS],
    Case("missing-frames", "frames.csv: file not found", _drop("frames.csv")),
    *[Case(f"missing-{n}", "", _drop(n), ok=True) for n in CSVS[1:]],
    Case("empty-frames", "frames.csv: empty", _set("frames.csv", b"")),
    *[Case(f"empty-{n}", "", _set(n, b""), ok=True) for n in CSVS[1:]],
    *[Case(f"torn-{n}", "", _text(n, lambda t: t[:-12]), ok=True) for n in CSVS],
    # frames.csv rows: exit 2 naming the row and the field
    Case(
        "frames-missing-column",
        "missing column 'seq'",
        _text("frames.csv", lambda t: t.replace("time_us,seq,", "time_us,sequence,", 1)),
    ),
    Case("frames-text-time", "frames.csv row 4, time_us: not an integer", _frames("soon")),
    Case("frames-nan-time", "frames.csv row 4, time_us: not an integer", _frames("nan")),
    Case("frames-inf-seq", "frames.csv row 4, seq: not an integer", _frames("inf", "seq")),
    Case("frames-5000-digits", "frames.csv row 4, time_us: not an integer: '99999", _frames(HUGE)),
    Case("frames-200kB-field", "frames.csv row 4", _frames("x" * 200_000, "filename")),
    Case("frames-duplicated-time", "frames.csv row 4, time_us", _dup_row("frames.csv", 2)),
    Case("frames-decreasing-time", "frames.csv row", _swap_rows("frames.csv", 2, 3)),
    Case(
        "frames-extra-column", "", _text("frames.csv", lambda t: t.replace("\n", ",x\n")), ok=True
    ),
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
        _text("ranges.csv", lambda t: t.replace("distance_m", "dist", 1)),
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
        edit=_text(f"{EUROC_CAM}/sensor.yaml", lambda t: t.replace("intrinsics", "intr")),
    ),
    Case(
        "euroc-nan-intrinsics",
        "sensor.yaml, intrinsics[0]: not a finite number",
        euroc=True,
        edit=_text(f"{EUROC_CAM}/sensor.yaml", lambda t: t.replace("[80.0,", "[nan,")),
    ),
    Case(
        "euroc-text-time",
        f"{EUROC_CAM}/data.csv row 3, timestamp",
        euroc=True,
        edit=_text(f"{EUROC_CAM}/data.csv", lambda t: t.replace("1033333000,", "soon,", 1)),
    ),
    Case(
        "euroc-dotdot",
        "'..' in file name",
        euroc=True,
        edit=_text(f"{EUROC_CAM}/data.csv", lambda t: t.replace(",1033333000.png", ",../x.png")),
    ),
    Case(
        "euroc-truth-junk",
        "state_groundtruth_estimate0/data.csv",
        euroc=True,
        ok=True,
        edit=_text(
            "mav0/state_groundtruth_estimate0/data.csv",
            lambda t: t.replace(",1.0,0.0,0.0,0.0\n", ",0,0,0,0\n", 1),
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


@pytest.fixture(scope="module")
def bases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Files]:
    root = tmp_path_factory.mktemp("bases")
    write_recording(root / "ours")
    write_euroc(root / "euroc")
    return {"ours": snapshot(root / "ours"), "euroc": snapshot(root / "euroc")}


class Opened:
    """The paths this process opens while ``recording`` (an audit hook: os.open and open()
    raise the ``open`` event before the kernel is asked)."""

    paths: ClassVar[list[str]] = []
    recording = False
    installed = False

    @classmethod
    def hook(cls, event: str, args: tuple) -> None:  # type: ignore[type-arg]
        if cls.recording and event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
            cls.paths.append(os.fsdecode(args[0]))

    @classmethod
    @contextlib.contextmanager
    def during(cls) -> Iterator[list[str]]:
        """Record the paths opened inside the block."""
        if not cls.installed:
            sys.addaudithook(cls.hook)
            cls.installed = True
        cls.paths = []
        cls.recording = True
        try:
            yield cls.paths
        finally:
            cls.recording = False


def _build(case: Case, bases: dict[str, Files], tmp_path: Path) -> tuple[Path, Path]:
    """The case's dataset folder and the folder outside it (valid images and files that a
    reader escaping the folder would happily use)."""
    base = bases["euroc" if case.euroc else "ours"]
    outside = materialise(base, tmp_path / "outside")
    shutil.copy(outside / (EUROC_FIRST if case.euroc else IMG0), outside / "x.png")
    files = dict(base)
    if case.name == "absolute-path":
        replace_field(files, "frames.csv", 3, "filename", str(outside / "x.png"))
    case.edit(files)
    folder = materialise(files, tmp_path / "ds" / "case")
    case.place(folder, outside)
    return folder, outside


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_a_hostile_dataset_is_refused_in_one_line_or_its_bad_rows_counted(
    case: Case, bases: dict[str, Files], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder, outside = _build(case, bases, tmp_path)
    capsys.readouterr()
    start = time.monotonic()
    with Opened.during() as paths:
        code = main(["eval", str(folder), "--out", str(tmp_path / "out"), "--no-progress"])
    elapsed = time.monotonic() - start
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    assert elapsed < 60, f"{case.name}: {elapsed:.1f} s"
    outside_real = os.path.realpath(outside)
    escaped = [
        p for p in paths if os.path.realpath(p).startswith((outside_real, "/etc/", "/dev/z"))
    ]
    assert not escaped, f"{case.name} opened {escaped}"
    lines = [line for line in err.splitlines() if not line.startswith("companion: warning:")]
    if case.ok:
        assert code == 0, err
        assert not lines, err
        warned = [line for line in err.splitlines() if "bad row" in line]
        assert (case.says in " ".join(warned)) if case.says else not warned, err
    else:
        assert code == 2, err
        assert len(lines) == 1 and lines[0].startswith("companion: dataset error: "), err
        assert case.says in lines[0], lines[0]


def test_there_are_at_least_56_cases() -> None:
    assert len(CASES) >= 56 and len({c.name for c in CASES}) == len(CASES)


def test_the_header_size_is_read_from_the_bytes() -> None:
    """PNG IHDR and JPEG SOF give the size without decoding; a PNG claiming another size is
    refused before decoding, and so is one that would decode to more than the cap."""
    import cv2
    import numpy as np

    img = np.zeros((72, 96, 3), dtype=np.uint8)
    for ext, kind in ((".png", "PNG"), (".jpg", "JPEG")):
        header = image_header(bytes(cv2.imencode(ext, img)[1]))
        assert header is not None and (header.kind, header.width, header.height) == (kind, 96, 72)
    claims = set_png_size(png_of(96, 72), 20_000, 20_000)
    with pytest.raises(DatasetError, match="PNG of 20000 x 20000 px"):
        check_image_header(claims, "frame 3", (96, 72))
    with pytest.raises(DatasetError, match="would take 20736 bytes decoded"):
        check_image_header(png_of(96, 72), "frame 3", (96, 72), max_decoded=1000)


BOMB_PROBE = textwrap.dedent(
    """
    import sys, time
    from companion.drivers.dataset import open_dataset
    from companion.errors import DatasetError
    ds = open_dataset(sys.argv[1])
    start = time.monotonic()
    try:
        ds.load_frame(0)
        print("decoded")
    except DatasetError as e:
        # VmHWM: this program's own peak (ru_maxrss keeps the parent's across exec)
        with open("/proc/self/status") as fh:
            peak_kb = next(int(x.split()[1]) for x in fh if x.startswith("VmHWM:"))
        print(f"{time.monotonic() - start:.4f} {peak_kb}")
        print(e)
    """
)


def test_a_32k_png_bomb_is_refused_in_under_a_second_below_300_mb(
    bases: dict[str, Files], tmp_path: Path
) -> None:
    """A 32768 x 32768 grey PNG of about 1 MB (1 GB of pixels; eval took 10.9 GB before the
    header check): refused from its header, in < 1 s, peak RSS < 300 MB."""
    files = dict(bases["ours"])
    files[IMG0] = png_bomb(32_768)
    assert len(files[IMG0]) < 2_000_000
    folder = materialise(files, tmp_path / "bomb")
    r = subprocess.run(
        [sys.executable, "-c", BOMB_PROBE, str(folder)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert r.returncode == 0, r.stderr
    seconds, rss_kb = r.stdout.split("\n")[0].split()
    assert "PNG of 32768 x 32768 px" in r.stdout
    ms, mb = float(seconds) * 1e3, int(rss_kb) / 1024
    print(f"32k x 32k PNG bomb refused in {ms:.1f} ms, peak RSS {mb:.0f} MB")
    assert float(seconds) < 1.0 and int(rss_kb) < 300 * 1024
    started = time.monotonic()
    code = main(["eval", str(folder), "--out", str(tmp_path / "out"), "--no-progress"])
    assert code == 2 and time.monotonic() - started < 30


def test_a_fifo_image_is_refused_at_once(bases: dict[str, Files], tmp_path: Path) -> None:
    """The reader opens a FIFO frame without blocking (no writer ever comes) and refuses it by
    its type; so does load_frame when the FIFO appears after the folder was opened."""
    folder = materialise(bases["ours"], tmp_path / "fifo")
    ds = open_dataset(folder)
    make_fifo(folder / "images" / "000003.png")
    start = time.monotonic()
    with pytest.raises(DatasetError, match=r"frame 3 .* is a FIFO"):
        ds.load_frame(3)
    assert time.monotonic() - start < 1.0
    with pytest.raises(DatasetError, match=r"frame 3 .* is a FIFO"):
        open_dataset(folder)


def test_the_folder_camera_refuses_what_eval_refuses(
    bases: dict[str, Files], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`companion config` with camera_url = folder:PATH on a dataset whose frames.csv points
    outside: exit 2 naming service.camera_url (it was a traceback, exit 1)."""
    files = dict(bases["ours"])
    replace_field(files, "frames.csv", 2, "filename", "../../outside/x.png")
    folder = materialise(files, tmp_path / "cam")
    config = tmp_path / "c.toml"
    config.write_text(
        f'[service]\ncamera_url = "folder:{folder}"\n'
        f'status_socket = "{tmp_path / "s.sock"}"\nstate_dir = "{tmp_path}"\n'
    )
    assert main(["config", "--config", str(config)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("companion: config error: service.camera_url:")
    assert "frames.csv row 3, filename" in err[0]


def test_the_memory_budget_stops_eval_cleanly(bases: dict[str, Files], tmp_path: Path) -> None:
    """--max-memory-mb below what the eval needs: exit 2 and one line, not a kill."""
    folder = materialise(bases["ours"], tmp_path / "budget")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "companion.cli",
            "eval",
            str(folder),
            "--out",
            str(tmp_path / "o"),
            "--no-progress",
            "--max-memory-mb",
            "60",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "--max-memory-mb" in lines[0], r.stderr


def test_the_time_budget_stops_eval_cleanly(bases: dict[str, Files], tmp_path: Path) -> None:
    folder = materialise(bases["ours"], tmp_path / "slow")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "companion.cli",
            "eval",
            str(folder),
            "--out",
            str(tmp_path / "o"),
            "--no-progress",
            "--timeout-s",
            "0.05",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "--timeout-s 0.05" in lines[0], r.stderr


def test_the_folder_camera_replays_a_hostile_time_gap_as_a_short_pause(
    bases: dict[str, Files], tmp_path: Path
) -> None:
    """A frame stamped 2**61 us after the one before (a valid, increasing time): the `folder:`
    camera of `companion run` slept through it (forever); now a pause of at most
    MAX_REPLAY_GAP_S."""
    from companion.drivers.camera import MAX_REPLAY_GAP_S, FolderSource

    files = dict(bases["ours"])
    lines = files["frames.csv"].decode().split("\n")
    for row in range(3, len([x for x in lines if x])):
        fields = lines[row].split(",")
        fields[0] = str(int(fields[0]) + 2**61)
        lines[row] = ",".join(fields)
    files["frames.csv"] = "\n".join(lines).encode()
    source = FolderSource(materialise(files, tmp_path / "gap"), realtime=True)
    start = time.monotonic()
    frames = []
    for frame in source.frames():
        frames.append(frame)
        if len(frames) == 4:
            break
    source.close()
    assert len(frames) == 4 and time.monotonic() - start < MAX_REPLAY_GAP_S + 2.0


def test_a_euroc_data_csv_without_its_header_comment_keeps_every_frame(
    bases: dict[str, Files], tmp_path: Path
) -> None:
    files = dict(bases["euroc"])
    edit_text(files, f"{EUROC_CAM}/data.csv", lambda t: t.split("\n", 1)[1])
    edit_text(
        files,
        "mav0/state_groundtruth_estimate0/data.csv",
        lambda t: t.split("\n", 1)[1],
    )
    ds = open_dataset(materialise(files, tmp_path / "euroc"))
    assert len(ds) == 8 and len(ds.gt_times_us) == 8 and not ds.skipped
