"""``folder:PATH``: a recorded dataset (ours or EuRoC, read through drivers/dataset) replayed
at its rate or as fast as possible, stamped so that its first frame is "now"."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from companion.drivers.camera.source import CameraSource, CaptureRequest
from companion.types import CameraFrame

if TYPE_CHECKING:
    pass


MAX_REPLAY_GAP_S = 1.0  # FolderSource: a longer gap between two frames is replayed as this


class FolderSource(CameraSource):
    """A recorded dataset (ours or EuRoC) replayed at its rate (or as fast as possible), read
    under drivers/safe_files.py's discipline (nothing outside the folder, regular files only,
    each image's size checked before it is decoded); a gap in its time stamps is replayed as
    MAX_REPLAY_GAP_S at most."""

    finite = True

    def __init__(
        self, path: Path, realtime: bool = True, request: CaptureRequest | None = None
    ) -> None:
        super().__init__(request)
        from companion.drivers.dataset import open_dataset

        self.dataset = open_dataset(path)
        self.realtime = realtime

    def _read(self) -> Iterator[CameraFrame]:
        t_start: int | None = None
        shift = 0
        for ev in self.dataset.events():
            if self.closed:
                return
            if not isinstance(ev, CameraFrame):
                continue
            now_us = time.monotonic_ns() // 1000
            if t_start is None:
                t_start, shift = ev.time_us, now_us - ev.time_us
            if self.realtime:
                wait = (ev.time_us + shift - now_us) * 1e-6
                if wait > MAX_REPLAY_GAP_S:  # a gap in the recording (or a hostile time
                    # stamp, 2**62 us ahead): replayed as a short pause, not slept through
                    shift -= int((wait - MAX_REPLAY_GAP_S) * 1e6)
                    wait = MAX_REPLAY_GAP_S
                if wait > 0:
                    time.sleep(wait)
            else:
                shift = now_us - ev.time_us  # as fast as possible: stamp with "now"
            yield CameraFrame(ev.time_us + shift, ev.seq, ev.image_bgr)
