"""`companion dataset convert SRC DST` (drivers/dataset/convert.py): a flight recording from a
folder into one MCAP file and back, losslessly: the same frames (image bytes), samples in the
same ingest order, held flags and published poses, and the same replay, bit for bit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from peers.clip_recordings import CLIP, record_clip

from companion.cli import main
from companion.drivers.dataset import Dataset, open_dataset, read_poses_csv
from companion.drivers.dataset.convert import encoded_frame


def same_recording(a: Dataset, b: Dataset) -> None:
    """Frames (times, seqs, held, image bytes), every sample with the frame it was fed
    before, and every published pose: equal in every bit."""
    assert len(a) == len(b) and np.array_equal(a.frame_times_us, b.frame_times_us)
    assert a.frame_seqs is not None and b.frame_seqs is not None
    assert np.array_equal(a.frame_seqs, b.frame_seqs)
    assert (a.frame_held is None) == (b.frame_held is None)
    assert all(encoded_frame(a, k) == encoded_frame(b, k) for k in range(len(a)))
    assert a.ranges == b.ranges and a.fed_before is not None and b.fed_before is not None
    for x, y in zip(a.fed_before, b.fed_before, strict=True):
        assert np.array_equal(x, y)
    assert len(a.attitudes) == len(b.attitudes)
    for p, q in zip(a.attitudes, b.attitudes, strict=True):
        assert p.time_us == q.time_us and np.array_equal(p.quat_wxyz, q.quat_wxyz)
        assert np.array_equal(p.rates_rad_s, q.rates_rad_s)
    assert len(a.published) == len(b.published) > 0
    for p, q in zip(a.published, b.published, strict=True):
        assert (p.time_us, p.reset_counter, p.quality_pct) == (
            q.time_us,
            q.reset_counter,
            q.quality_pct,
        )
        for u, v in (
            (p.position_ned_m, q.position_ned_m),
            (p.quat_wxyz, q.quat_wxyz),
            (p.velocity_ned_m_s, q.velocity_ned_m_s),
        ):
            assert np.array_equal(u, v, equal_nan=True)
    assert a.config is not None and b.config is not None
    assert a.config.camera == b.config.camera and a.config.vo == b.config.vo


def test_folder_to_mcap_and_back_is_lossless_and_replays_the_same(tmp_path: Path) -> None:
    rec, sent = record_clip(tmp_path / "rec", frames=40, format="folder")
    assert rec.state == "closed" and len(sent) >= 25
    folder = open_dataset(tmp_path / "rec")
    assert main(["dataset", "convert", str(tmp_path / "rec"), str(tmp_path / "rec.mcap")]) == 0
    mcap = open_dataset(tmp_path / "rec.mcap")
    assert mcap.complete and mcap.meta["image"] == "colour"  # a folder's frames: colour PNG
    same_recording(folder, mcap)
    assert main(["dataset", "convert", str(tmp_path / "rec.mcap"), str(tmp_path / "back")]) == 0
    back = open_dataset(tmp_path / "back")
    same_recording(folder, back)
    assert back.meta["created"] == folder.meta["created"]
    replays = []
    for name in ("rec", "rec.mcap", "back"):
        out = tmp_path / f"replay-{name}"
        assert main(["eval", str(tmp_path / name), "--out", str(out), "--no-progress"]) == 0
        replays.append((out / "poses.csv").read_text())
        check = json.loads((out / "replay.json").read_text())
        assert check["matched"] == check["published"] == len(sent)
    assert replays[0] == replays[1] == replays[2]  # the same poses, to the last digit
    assert len(read_poses_csv(tmp_path / "replay-rec" / "poses.csv")) == len(sent)


def test_convert_refuses_what_it_cannot_convert(tmp_path: Path, capsys) -> None:
    """A dataset that is no flight recording, and a destination that is taken: exit 2 with
    one line naming it."""
    assert main(["dataset", "convert", str(CLIP), str(tmp_path / "clip.mcap")]) == 2
    assert "not a flight recording" in capsys.readouterr().err
    (tmp_path / "taken.mcap").write_bytes(b"mine")
    record_clip(tmp_path / "rec", frames=3)
    assert (
        main(["dataset", "convert", str(tmp_path / "rec.mcap"), str(tmp_path / "taken.mcap")]) == 2
    )
    assert "exists" in capsys.readouterr().err
    assert (tmp_path / "taken.mcap").read_bytes() == b"mine"
