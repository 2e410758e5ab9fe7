"""The pipeline worker: each frame the intake picks, with the samples queued since the last,
through the ``Pipeline`` on a worker thread, then to the publisher.

Inputs: frames (``FrameIntake.next_frame``), ranges, attitudes and IMU samples
(``AutopilotSession.take_samples``). Outputs: poses to the ``Publisher``, the frames and
samples to the recorder, ``status`` (the pipeline's frozen ``PipelineStatus`` snapshot, the
only thing the event loop reads of the pipeline), ``vo_state``, the
processing counters and timings in ``ServiceStats``; with the live page, while somebody
watches, each frame's view into its 1-slot holder (``LatestView.offer``: references only), and
each pose sent to ``on_sent`` (on the loop).

Threads: the worker thread (``asyncio.to_thread``; OpenCV and numpy release the GIL) owns the
Pipeline and replaces ``status`` (a reference swap, atomic in CPython) after each frame. The
process's garbage collections run there too, after each frame's work (``GcPacing``): one
started by an allocation on another thread would stop the worker mid-frame.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

from companion.gc_pacing import GcPacing
from companion.pipeline import Pipeline, PipelineStatus, Sample
from companion.service.autopilot_session import AutopilotSession
from companion.service.frame_intake import FrameIntake
from companion.service.publisher import Publisher
from companion.service.recorder import Recorder
from companion.service.runtime import Runtime
from companion.service.web_view import LatestView
from companion.types import (
    AttitudeSample,
    CameraFrame,
    ImuSample,
    PoseEstimate,
    RangeSample,
    VoState,
)
from companion.vo.frame_clock import jitter_warning

log = logging.getLogger("companion.service")

MAX_CONSECUTIVE_PIPELINE_ERRORS = 30  # about a second of frames: then the service ends


class PipelineWorker:
    """Frames and samples through the pipeline, poses to the publisher."""

    def __init__(
        self,
        rt: Runtime,
        pipeline: Pipeline,
        intake: FrameIntake,
        session: AutopilotSession,
        publisher: Publisher,
        recorder: Recorder,
        view: LatestView | None = None,
    ) -> None:
        self.rt = rt
        self.pipeline = pipeline  # touched by the worker thread only
        self.intake = intake
        self.session = session
        self.publisher = publisher
        self.recorder = recorder
        self.view = view  # the live page's holder (None: no page)
        self.on_sent: Callable[[PoseEstimate], None] | None = None  # each pose sent, on the loop
        self.status: PipelineStatus = pipeline.status()  # the worker replaces it
        self.vo_state = VoState.INITIALIZING  # of the last frame processed
        self._vo_start_logged = -1  # vo_resets of the last initialisation logged
        self._compass_logged = (False, False)  # (first fix logged, final one logged)
        self._jitter_logged = False  # the camera clock's jitter was logged
        # Python's garbage collector after each frame's work, not inside it (closed by the app)
        self.gc = GcPacing()

    async def loop(self) -> None:
        """Each frame, as the intake picks it, through the pipeline; a failure on one frame
        is logged, counted and skipped, MAX_CONSECUTIVE_PIPELINE_ERRORS in a row end the
        service (systemd restarts it)."""
        s = self.rt.stats
        failures = 0
        while not self.rt.stopping:
            frame = self.intake.next_frame()
            if frame is None:
                await self.intake.ready.wait()
                self.intake.ready.clear()
                continue
            ranges, atts, imus = self.session.take_samples()
            t0 = time.perf_counter()
            try:
                pose = await asyncio.to_thread(self.process, frame, ranges, atts, imus)
            except Exception:
                # a bug on one frame must not take the autopilot's estimate down for good
                log.exception("pipeline failed on frame %d", frame.seq)
                s.pipeline_errors += 1
                failures += 1
                if failures >= MAX_CONSECUTIVE_PIPELINE_ERRORS:
                    raise
                continue
            failures = 0
            s.process_ms.append((time.perf_counter() - t0) * 1e3)
            s.frames_processed += 1
            self._after_frame()
            sent = s.published
            self.publisher.publish(frame, pose)
            if pose is not None and s.published > sent and self.on_sent is not None:
                self.on_sent(pose)
            await asyncio.to_thread(self._background)  # after the send
            s.cycle_ms.append((time.perf_counter() - t0) * 1e3)

    def process(
        self,
        frame: CameraFrame,
        ranges: list[RangeSample],
        atts: list[AttitudeSample],
        imus: list[ImuSample] | None = None,
    ) -> PoseEstimate | None:
        """Worker thread: feed the queued samples, then the frame."""
        p = self.pipeline
        imus = imus or []
        samples: list[Sample] = [*atts, *imus, *ranges]  # each stream in its time order
        for sample in samples:
            p.feed(sample)
        held = p.hold_for_attitude(frame, autopilot_seen=self.rt.stats.autopilot_heartbeat_ns > 0)
        # recorded with whether it reached the VO: a replay then holds the same frames (the
        # wait depends on when the autopilot's HEARTBEAT came, which a replay does not have)
        self.recorder.frame(frame, ranges, atts, imus, held)  # a reference into its queue
        pose = None if held else p.feed_frame(frame, checked=True)  # checked by the intake
        self.status = p.status()  # a new frozen snapshot: the loop reads only this
        if self.recorder.state == "recording":  # for its viewers, with the autopilot's clock
            sync = self.session.sync
            offset_us = sync.offset_at(self.rt.clock()) / 1e3 if sync.converged else None
            self.recorder.pipeline_state(frame.time_us, self.status, offset_us)
        if self.view is not None:  # nothing at all while nobody watches
            # a held frame never reached the VO: the outputs left are an earlier frame's
            vo, scale_input = (None, None) if held else (p.vo_output, p.scale_input)
            self.view.offer(frame, vo, scale_input, self.status, pose)
        return pose

    def _background(self) -> None:
        """Worker thread: the keyframe work the pose did not need, then a new snapshot; then
        the garbage collector's due work (companion/gc_pacing.py)."""
        if self.pipeline.background_work():
            self.status = self.pipeline.status()
        self.gc.after_frame()

    def _after_frame(self) -> None:
        """On the loop, after a frame: the VO's state kept; its start and heading logged;
        once, a camera clock that jitters (its frames are then re-timed)."""
        self.vo_state = VoState[self.status.vo_state]
        clock = self.status.clock
        if clock is not None and clock.retimed and not self._jitter_logged:
            self._jitter_logged = True
            log.warning(jitter_warning(clock))
        if self.vo_state == VoState.TRACKING:
            self._log_vo_start(self.status)
            self._log_compass_heading(self.status)

    def _log_vo_start(self, p: PipelineStatus) -> None:
        """Once per VO initialisation: which heading its frame has (the autopilot's, or none:
        then our north is the camera's first heading and the autopilot's frame is turned)."""
        if p.vo_resets == self._vo_start_logged:
            return
        self._vo_start_logged = p.vo_resets
        if p.vo_heading_deg is None:
            log.warning(
                "VO tracking (initialisation %d) without an autopilot attitude at hand: its "
                "heading 0 is the camera's first, not the autopilot's",
                p.vo_resets + 1,
            )
        else:
            log.info(
                "VO tracking (initialisation %d): its frame's heading %.2f deg (the autopilot's)",
                p.vo_resets + 1,
                p.vo_heading_deg,
            )

    def _log_compass_heading(self, p: PipelineStatus) -> None:
        """vo.heading_source = magnetometer: once when our compass first sets the frame's
        heading, and once when it stops refining it (the vehicle moved)."""
        if p.mag_heading_samples == 0 or p.vo_heading_deg is None:
            return
        ended = p.mag_heading_final
        if self._compass_logged == (True, ended):
            return
        self._compass_logged = (True, ended)
        log.info(
            "VO frame's heading %.2f deg from our compass (%d samples at rest, sigma %.2f deg)%s",
            p.vo_heading_deg,
            p.mag_heading_samples,
            p.mag_heading_sigma_deg or 0.0,
            ": final, the vehicle moved" if ended else "; refined until the vehicle moves",
        )
