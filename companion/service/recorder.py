"""The flight recorder: what the service's pipeline was fed, as a dataset ``companion eval``
replays through the same Pipeline (docs/dataset.md, "Flight recordings", "MCAP recordings"):
one MCAP file by default (``record.format = "mcap"``: ``McapDatasetWriter``; Foxglove and
PlotJuggler open it), or a folder of our format (``"folder"``: ``DatasetWriter``).

The service hands over, on the pipeline's worker thread and before it feeds them, each frame
with the attitudes and ranges queued for it (``frame``), and from the event loop each pose it
sent (``pose``). Both only put a reference into a bounded queue (``record.queue_frames``): no
disk work, no encoding, no waiting. A writer thread encodes the images (PNG: lossless, so the
replay is fed the same bytes; grey in an MCAP file unless d-Pose reads colour) and appends them.

The flight output always wins: a full queue (the disk is slower than the camera), the disk
budget (``record.max_mb``), too little free space (``record.min_free_mb``) or a write error
stops the recording cleanly, never the service; the folder then holds a valid dataset up to its
last frame, and the reason is said once (the service's warnings, log, MQTT) and kept in the
status. A recording is not resumed after it stopped: a replay must see every frame the
pipeline saw, so a recording with a hole would not replay what was flown.

The recording is its own (the service runs as root): the file ``record.dir``.mcap, or the
folder ``record.dir``, made new at the start (a folder: or an empty one we own that nobody else
may write into, made beforehand, e.g. by systemd). Anything else there (an earlier run's when
``record.dir`` has no ``{start}``, a symbolic link, a folder others may write into) is left
alone: the recording goes into a new sibling ``-2``, ``-3``... and the service says so; when
none can be made, it runs without a recording and says why. Every file is created new, never
through a link (O_EXCL | O_NOFOLLOW, drivers/files.py).
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import shutil
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion import __version__
from companion.config import Config, RecordOptions
from companion.drivers.dataset.recording import (
    RecordingWriter,
    empty_folder_of_ours,
    image_mode,
    make_writer,
    recording_dir,
    recording_path,
)
from companion.errors import DatasetError
from companion.types import AttitudeSample, CameraFrame, ImuSample, PoseEstimate, RangeSample

log = logging.getLogger("companion.recorder")

SYNC_PERIOD_S = 1.0  # fsync this often (what a power cut keeps); MCAP: close the chunk too
CLOSE_TIMEOUT_S = 30.0  # at exit, wait this long at most for the queue to reach the disk
WRITER_NICE = 10  # the writer thread's niceness: on a busy board the pipeline goes first
SIBLING_ATTEMPTS = 1000  # record.dir taken: record into record.dir-2 .. record.dir-1000


@dataclass(frozen=True, slots=True)
class FrameRecord:
    """One frame as the pipeline took it, with the samples it was fed first (in that order);
    ``held``: the frame was held from the VO (a replay feeds its samples only)."""

    frame: CameraFrame
    ranges: Sequence[RangeSample]
    attitudes: Sequence[AttitudeSample]
    imus: Sequence[ImuSample] = ()
    held: bool = False


@dataclass(frozen=True, slots=True)
class Note:
    """For the recording's viewers, not its replay (an MCAP's /companion/state and /log): the
    pipeline's ``status`` after the frame of ``time_us`` with the autopilot clock's
    ``offset_us``, or (``status`` None) a ``text`` line of ``level`` said by ``name``."""

    time_us: int
    status: Any = None
    offset_us: float | None = None
    text: str = ""
    level: str = "INFO"
    name: str = ""


Item = FrameRecord | PoseEstimate | Note


class Recorder:
    """``with Recorder(options, config).running(notify):`` record; ``frame`` / ``pose`` from
    any thread, never blocking. Disabled (every call a no-op) when ``options.dir`` is empty."""

    def __init__(self, options: RecordOptions, config: Config) -> None:
        self.options = options
        self.config = config
        self.enabled = bool(options.dir)
        # record.dir as configured; start() records there (or beside it)
        self.path = recording_dir(options.dir) if self.enabled else None
        self.state = "recording" if self.enabled else "off"
        self.reason = ""
        self.frames_not_recorded = 0  # frames the pipeline got after the recording stopped
        # unbounded, but at most options.queue_frames frames in it (poses are small)
        self._queue: queue.Queue[Item | None] = queue.Queue()
        self._queued_frames = 0
        self._lock = threading.Lock()
        self._writer: RecordingWriter | None = None
        self._thread: threading.Thread | None = None
        self._notify: Callable[[str], object] = log.warning
        self._frames = 0
        self._poses = 0
        self._bytes = 0
        self._cpu_s = 0.0

    # ------------------------------------------------------------------ lifecycle
    def start(self, notify: Callable[[str], object] | None = None) -> None:
        """Create the recording and start the writer thread. ``notify(text)`` tells the
        operator why a recording stopped (called from any thread). A recording that cannot be
        written leaves the service running without one (said through ``notify``)."""
        if notify is not None:
            self._notify = notify
        if not self.enabled or self.path is None:
            return
        o = self.options
        try:
            self.path, self._writer = self._claim(self.path)
        except Exception as e:  # whatever it is, the service runs on without a recording
            self._stop(f"cannot record into {self.path}: {e}")
            return
        what = f"{o.format}, {image_mode(o, self.config)} {o.image_format}"
        log.info("recording into %s (%s, budget %g MB)", self.path, what, o.max_mb)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def _claim(self, wanted: Path) -> tuple[Path, RecordingWriter]:
        """The recording, made now: ``wanted`` (from record.dir), or when anything is there
        already, a new sibling ``-2``, ``-3``... (said through notify); a folder may be an
        empty one of ours made beforehand (systemd's StateDirectory=). Made here, it is new
        and ours: no link can have been planted in it. OSError when none can be made (the
        caller records nothing and says why)."""
        wanted.parent.mkdir(parents=True, exist_ok=True)
        o = self.options
        for k in range(1, SIBLING_ATTEMPTS + 1):
            path = recording_path(wanted, o, k)
            ours = o.format == "folder" and empty_folder_of_ours(path)
            try:
                writer = make_writer(path, self.config, o, __version__, ours)
            except FileExistsError:
                continue
            if k > 1:
                self._notify(
                    f"recorder: {recording_path(wanted, o)} exists and is not an empty folder of "
                    f"ours; recording into {path} instead (put {{start}} in record.dir for "
                    "a recording per run)"
                )
            return path, writer
        raise FileExistsError(
            f"{wanted} and its siblings up to -{SIBLING_ATTEMPTS} all exist; clear them out "
            "or put {start} in record.dir"
        )

    def close(self) -> None:
        """Write what is queued, then mark the recording complete (meta.toml). A disk that
        does not take it within CLOSE_TIMEOUT_S leaves the recording unfinished (readable up
        to its last complete frame)."""
        if self._thread is None:
            return
        self._queue.put(None)
        self._thread.join(CLOSE_TIMEOUT_S)
        if self._thread.is_alive():
            log.warning("recorder: the disk did not take the queued frames at exit")
        self._thread = None
        with self._lock:
            if self.state == "recording":
                self.state = "closed"
        if self.path is not None:
            log.info(
                "recorded %d frames, %d poses (%.1f MB) into %s",
                self._frames,
                self._poses,
                self._bytes / 1e6,
                self.path,
            )

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def running(self, notify: Callable[[str], object] | None = None) -> Recorder:
        """``start(notify)`` and return self, for ``with`` / ``ExitStack.enter_context``."""
        self.start(notify)
        return self

    # ------------------------------------------------------------------ producers
    def frame(
        self,
        frame: CameraFrame,
        ranges: Sequence[RangeSample],
        attitudes: Sequence[AttitudeSample],
        imus: Sequence[ImuSample] = (),
        held: bool = False,
    ) -> None:
        """The frame the pipeline took, with the samples it was fed first (in the order it was
        fed them); ``held``: the frame was held from the VO (a replay feeds its samples only).
        Never blocks; a full queue stops the recording."""
        if self.state != "recording":
            if self.enabled:
                self._not_recorded(1)
            return
        with self._lock:
            full = self._queued_frames >= self.options.queue_frames
            if not full:
                self._queued_frames += 1
        if full:
            self._not_recorded(1)
            self._stop(
                f"the disk is slower than the camera ({self.options.queue_frames} frames "
                "waiting); the flight output is not affected"
            )
            return
        self._queue.put(FrameRecord(frame, list(ranges), list(attitudes), list(imus), held))

    def pose(self, pose: PoseEstimate) -> None:
        """A pose the service sent to the autopilot (the wire's reset_counter)."""
        if self.state == "recording":
            self._queue.put(pose)

    def pipeline_state(self, time_us: int, status: Any, offset_us: float | None) -> None:
        """The pipeline's frozen status after the frame of ``time_us`` (a reference) and the
        autopilot clock's offset (ours - its, [us]; None: not known yet)."""
        if self.state == "recording":
            self._queue.put(Note(time_us, status, offset_us))

    def log_line(self, time_us: int, text: str, level: str, name: str) -> None:
        """A line the service said (a warning, a STATUSTEXT): on the recording's /log."""
        if self.state == "recording":
            self._queue.put(Note(time_us, text=text, level=level, name=name))

    # ------------------------------------------------------------------ the writer thread
    def _run(self) -> None:
        """The writer thread: the only one that touches the DatasetWriter. After a stop it
        writes what was queued before it (consecutive frames), then closes the dataset."""
        writer = self._writer
        assert writer is not None
        with contextlib.suppress(OSError, AttributeError):  # Linux: per thread; else as is
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WRITER_NICE)
        last_sync = time.monotonic()
        try:
            while True:
                if time.monotonic() - last_sync > SYNC_PERIOD_S:  # also when frames pause
                    writer.sync()
                    last_sync = time.monotonic()
                try:
                    item = self._queue.get(timeout=0.2)
                except queue.Empty:
                    if self.state != "recording":
                        break  # stopped by a producer, and all it queued is written
                    continue
                if item is None:
                    break
                if isinstance(item, FrameRecord):
                    with self._lock:
                        self._queued_frames -= 1
                if isinstance(item, Note):
                    if item.status is not None:
                        writer.write_state(item.time_us, item.status, item.offset_us)
                    else:
                        writer.log(item.time_us, item.text, item.level, item.name)
                elif isinstance(item, PoseEstimate):
                    writer.write_pose(item)
                    self._poses += 1
                elif not self._write_frame(writer, item):
                    break  # over budget: stopped
                self._bytes = writer.bytes_written
                self._cpu_s = time.thread_time()  # the writer's own CPU time so far
        except (OSError, DatasetError) as e:
            self._stop(f"writing failed: {e}")
        except Exception as e:  # a bug: the recording ends, the service does not
            log.exception("recorder: failed")
            self._stop(f"failed: {type(e).__name__}: {e}")
        try:
            writer.close(self.reason)
        except OSError as e:
            log.warning("recorder: closing %s failed: %s", self.path, e)
        self._bytes = writer.bytes_written
        while True:  # what was queued after the stop is not written: let it go
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, FrameRecord):
                self._not_recorded(1)

    def _not_recorded(self, frames: int) -> None:
        with self._lock:
            self.frames_not_recorded += frames

    def _write_frame(self, writer: RecordingWriter, rec: FrameRecord) -> bool:
        """Encode and append one frame; False (and stopped) when it would break the budget."""
        encoded = writer.encode(rec.frame.image_bgr)
        need = writer.frame_bytes(encoded, len(rec.ranges), len(rec.attitudes), len(rec.imus))
        o = self.options
        if writer.bytes_written + need > o.max_mb * 1e6:
            self._stop(f"disk budget of {o.max_mb:g} MB reached (record.max_mb)")
            self._not_recorded(1)
            return False
        free = shutil.disk_usage(writer.path).free
        if free - need < o.min_free_mb * 1e6:
            self._stop(f"less than {o.min_free_mb:g} MB free on the disk (record.min_free_mb)")
            self._not_recorded(1)
            return False
        writer.write_frame(rec.frame, encoded, rec.ranges, rec.attitudes, rec.imus, rec.held)
        self._frames += 1
        return True

    def _stop(self, reason: str) -> None:
        """Stop recording (once) and say why; the writer thread then closes the dataset,
        valid up to its last frame. Safe from any thread."""
        with self._lock:
            if self.state != "recording":
                return
            self.state = "stopped" if self._writer is not None else "failed"
            self.reason = reason
        text = f"recorder: stopped after {self._frames} frames in {self.path}: {reason}"
        try:
            self._notify(text)
        except RuntimeError:  # the service's loop is already closed
            log.warning(text)

    # ------------------------------------------------------------------ status
    def status(self) -> dict[str, Any]:
        """The status's recorder section."""
        return {
            "enabled": self.enabled,
            "dir": str(self.path) if self.path is not None else None,
            "format": self.options.format,
            "state": self.state,
            "frames": self._frames,
            "poses": self._poses,
            "mb": self._bytes / 1e6,
            "writer_cpu_s": self._cpu_s,  # encoding and writing, on the writer thread
            "budget_mb": self.options.max_mb,
            "queued_frames": self._queued_frames,
            "reason": self.reason,
            "frames_not_recorded": self.frames_not_recorded,
        }
