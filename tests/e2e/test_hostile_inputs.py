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
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import pytest
from peers.hostile_cases import CASES, EUROC_CAM, EUROC_FIRST, IMG0, Case
from peers.hostile_datasets import (
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


@pytest.mark.parametrize(
    ("flags", "said"),
    [(["--max-memory-mb", "60"], "--max-memory-mb"), (["--timeout-s", "0.05"], "--timeout-s 0.05")],
    ids=["memory", "time"],
)
def test_a_budget_stops_eval_cleanly(
    bases: dict[str, Files], tmp_path: Path, flags: list[str], said: str
) -> None:
    """--max-memory-mb below what the eval needs, or --timeout-s shorter than it takes: exit 2
    and one line naming the flag, not a kill and no traceback."""
    folder = materialise(bases["ours"], tmp_path / "budget")
    argv = ["eval", str(folder), "--out", str(tmp_path / "o"), "--no-progress", *flags]
    r = subprocess.run(
        [sys.executable, "-m", "companion.cli", *argv],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and said in lines[0], r.stderr


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
