"""Frame intake: the camera read in its own thread, every frame checked, a short queue, and
the wait rule that picks the frame the pipeline takes next.

Inputs: the camera driver's frames (``CameraFrame``: exposure time in our clock [us]), the
recent processing times (``ServiceStats.process_ms`` [ms]). Outputs: ``next_frame()`` (the
oldest queued frame still worth a pose, or None), ``ready`` (set when a frame is queued), the
frame counters in ``ServiceStats``, the arrival times [ns] (``frame_times_ns``), the camera
fault in progress (``problem``; ``silent`` is set by the operator messages' health check).

Threads: the reader thread writes the queue, the arrival times, the counters and the frame
check only under ``lock`` (the loop reads them under it too), and reports a fault's start and
end with ``call_soon_threadsafe``.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.drivers.backoff import Backoff
from companion.service.runtime import Runtime
from companion.types import CameraFrame
from companion.vo.frame_check import FrameProblem

RECENT_PROCESS = 20  # frames whose median processing time rules which queued one can be sent
FRAME_QUEUE_MAX = 8  # frames waiting for the pipeline at most (memory bound; frame_wait_ms rules)


class FrameIntake:
    """The camera's frames from its reader thread to the pipeline's loop."""

    def __init__(
        self, rt: Runtime, camera: Any, check: Callable[[CameraFrame], FrameProblem | None]
    ) -> None:
        self.rt = rt
        self.camera = camera
        # the pipeline's one frame check (Pipeline.check_frame), run on every delivered frame
        # here on the reader thread: the worker feeds the frames it passes as checked
        self.check = check
        # frames waiting for the pipeline (bounded: the wait rule keeps it at a few)
        self.frames: deque[CameraFrame] = deque(maxlen=FRAME_QUEUE_MAX)
        self.lock = threading.Lock()
        self.ready = asyncio.Event()
        self.frame_times_ns: deque[int] = deque(maxlen=90)  # arrivals, for the camera fps
        self.problem: FrameProblem | None = None  # the camera fault in progress (the loop's)
        self.silent = False  # no frames for a while (the health check says)
        rt.stop_listeners.append(self.ready.set)

    def last_frame_ns(self, default: int) -> int:
        """When the last frame arrived [ns] (``default`` before the first)."""
        with self.lock:
            return self.frame_times_ns[-1] if self.frame_times_ns else default

    def next_frame(self) -> CameraFrame | None:
        """The oldest queued frame that can still be published: at most frame_wait_ms old
        (since exposure), and at most stale_frame_ms less the recent processing time (the
        median of the last RECENT_PROCESS frames), so that its pose is not too old to send
        once made; older ones are skipped (counted as dropped) while a newer frame exists.
        On a loaded machine (a climb's keyframes beside the simulator on 2 cores) frames were
        processed only to be found stale: 1.3-1.7 s without a pose sent, and PX4 stopped
        fusing us; a frame skipped before the work leaves the time to the next one."""
        o, s = self.rt.config.service, self.rt.stats
        limit_us = o.frame_wait_ms * 1e3
        recent = list(itertools.islice(reversed(s.process_ms), RECENT_PROCESS))
        if len(recent) == RECENT_PROCESS:
            limit_us = min(limit_us, (o.stale_frame_ms - float(np.median(recent))) * 1e3)
        with self.lock:
            now_us = self.rt.clock() / 1e3
            while len(self.frames) > 1 and now_us - self.frames[0].time_us > limit_us:
                self.frames.popleft()
                s.frames_dropped += 1
            return self.frames.popleft() if self.frames else None

    def _camera_problem(self, problem: FrameProblem | None) -> None:
        """A camera fault starts or ends (on the event loop): said once, not per frame."""
        prev, self.problem = self.problem, problem
        if problem is not None:
            self.rt.warn(f"camera: {problem.value} frames; not publishing")
        elif prev is not None:
            self.rt.warn(f"camera: usable frames again (after {prev.value} ones)")

    def _read(self, loop: asyncio.AbstractEventLoop, done: asyncio.Future[Any]) -> None:
        """The reader thread: every frame checked and counted, the usable ones queued;
        ``done`` gets the driver's error (None: the source ended)."""
        error: BaseException | None = None
        seen_problem = self.problem
        s = self.rt.stats
        try:
            for frame in self.camera.frames():
                if self.rt.stopping:
                    break
                # every delivered frame is checked (a few us), not only the ones the
                # pipeline gets to: a frozen frame must be compared with the frame
                # before it, not with the last one processed
                with self.lock:
                    problem = self.check(frame)
                    if problem != seen_problem:  # the loop owns self.problem
                        loop.call_soon_threadsafe(self._camera_problem, problem)
                        seen_problem = problem
                    s.frames_in += 1
                    self.frame_times_ns.append(self.rt.clock())
                    if problem is not None:  # never reaches the pipeline: no pose
                        s.frames_rejected += 1
                        continue
                    if len(self.frames) == self.frames.maxlen:
                        s.frames_dropped += 1  # the oldest goes
                    self.frames.append(frame)
                loop.call_soon_threadsafe(self.ready.set)
        except Exception as e:  # a driver error: reported, the source is reopened
            error = e

        def finish() -> None:
            if not done.done():
                done.set_result(error)

        with contextlib.suppress(RuntimeError):  # the loop may be closed at exit
            loop.call_soon_threadsafe(finish)

    async def camera_loop(self) -> None:
        """Read the camera in a daemon thread (a blocked driver call can never hold up the
        exit). A finite source (a file, a folder) that ends stops the service; a live one that
        ends or fails is reopened with capped, jittered backoff."""
        loop = asyncio.get_running_loop()
        backoff, reported = Backoff(0.5, 5.0), False
        while not self.rt.stopping:
            done: asyncio.Future[BaseException | None] = loop.create_future()
            frames_before = self.rt.stats.frames_in
            threading.Thread(
                target=self._read, args=(loop, done), name="camera", daemon=True
            ).start()
            error = await done
            if self.rt.stopping:
                return
            if error is None and self.camera.finite:
                self.rt.warn("camera: the recording ended; stopping")
                self.rt.stop()
                return
            if self.rt.stats.frames_in > frames_before:  # it worked for a while: retry soon
                backoff.reset()
                reported = False
            if not reported:  # once per outage, not once per attempt
                why = f"failed: {error}" if error else "stream ended"
                self.rt.warn(f"camera: {why}; reopening until it is back")
                reported = True
            await self.rt.sleep(backoff.next_s())
