"""Operator messages: what the people at the ground station must hear, said once.

Inputs: the service's own state on the event loop (the frame intake's arrivals and fault, the
pipeline's status snapshot, the autopilot's HEARTBEAT, the serial rangefinders' errors, the
link's rival). Outputs: warnings (``Runtime.warn``: log, status, MQTT) from the health check,
and STATUSTEXT on the link: events from transitions of ``statustext.OperatorState``
snapshots, rate-limited by ``statustext.Limiter``; at the start the start events, at exit
what is pending and why we stop.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from companion.drivers import messages
from companion.service import frame_events, statustext
from companion.service.frame_intake import FrameIntake
from companion.service.gps_frame import GpsFrame
from companion.service.runtime import Runtime
from companion.service.worker import PipelineWorker
from companion.types import VoState

CAMERA_SILENT_S = 1.0  # no frame for this long (or 10 frame periods, if longer): said, shown
AUTOPILOT_UNHEARD_S = 5.0  # no heartbeat this long after the start: said, with the link's error
HEALTH_PERIOD_S = 0.5
# MAV_SEVERITY 0..7 (EMERGENCY .. DEBUG) as a recording's foxglove.Log level
LOG_LEVEL_OF_SEVERITY = ("FATAL", "FATAL", "FATAL", "ERROR", "WARNING", "INFO", "INFO", "DEBUG")


@dataclass(eq=False, repr=False)
class OperatorMessages:
    """The health check's warnings and the STATUSTEXT to the ground station."""

    rt: Runtime
    link: Any
    camera: Any
    intake: FrameIntake
    worker: PipelineWorker
    tfminis: Sequence[Any]
    camera_url_shown: str
    gps: GpsFrame | None = None  # [gps] align: its state in the STATUSTEXT

    def __post_init__(self) -> None:
        st = self.rt.config.service.statustext
        self.limiter = statustext.Limiter(st.key_interval_s, st.burst, st.rate_hz, st.prefix)
        self._operator = statustext.INITIAL
        self._attitude_held = statustext.Held(statustext.ATTITUDE_HOLD_S)
        self._dpose_lock = statustext.RecentIncrease(statustext.DPOSE_LOCK_HOLD_S)
        self._text_id = 0  # of the last chunked STATUSTEXT

    # ------------------------------------------------------------------ health
    async def health_loop(self) -> None:
        """What an operator must hear about even when nothing raises: a camera that delivers
        nothing (a killed stream, a stalled driver, nobody listening), an autopilot never heard
        since the start (a wrong port or device), a serial rangefinder that cannot be opened."""
        rt, intake = self.rt, self.intake
        started = rt.clock()
        silent_after_s = max(CAMERA_SILENT_S, 10.0 / rt.config.camera.rate_hz)
        unheard_said = False
        rf_said: dict[int, str] = {}
        while not rt.stopping:
            now = rt.clock()
            silent_s = (now - intake.last_frame_ns(started)) * 1e-9
            if silent_s > silent_after_s and not intake.silent:
                intake.silent = True
                rt.warn(
                    f"camera: no frames for {silent_s:.1f} s from {self.camera_url_shown}; "
                    "not publishing"
                )
            elif intake.silent and silent_s <= silent_after_s:
                intake.silent = False
                rt.warn("camera: frames again")
            if (
                not unheard_said
                and not rt.stats.autopilot_heartbeat_ns
                and (now - started) * 1e-9 > AUTOPILOT_UNHEARD_S
            ):
                unheard_said = True
                why = self.link.stats.last_error
                rt.warn(
                    f"autopilot: no heartbeat on {rt.config.service.mavlink_url} for "
                    f"{AUTOPILOT_UNHEARD_S:g} s" + (f" ({why})" if why else "")
                )
            for drv in self.tfminis:
                err = drv.last_error
                if err and rf_said.get(drv.sensor_id) != err:
                    rt.warn(f"rangefinder {drv.sensor_id}: {err}")
                elif not err and drv.sensor_id in rf_said:
                    rt.warn(f"rangefinder {drv.sensor_id}: {drv.device} open")
                if err:
                    rf_said[drv.sensor_id] = err
                else:
                    rf_said.pop(drv.sensor_id, None)
            await rt.sleep(HEALTH_PERIOD_S)

    # ------------------------------------------------------------------ STATUSTEXT
    def state(self, now: int) -> statustext.OperatorState:
        """What the operator cares about now [``now``: ns], from the service's own state."""
        s, p = self.rt.stats, self.worker.status
        camera = "no frames" if self.intake.silent else None
        if camera is not None and self.camera.last_error_brief:  # a size refused, say which
            camera = f"no frames ({self.camera.last_error_brief})"
        if camera is None and self.intake.problem is not None:
            camera = self.intake.problem.value
        tracking = p.vo_state == VoState.TRACKING.name
        t_s = now * 1e-9
        dpose_armed, dpose_used = self.worker.status.dpose_armed, self.worker.status.dpose_used
        hb = s.autopilot_heartbeat_ns
        frame = self.gps.out if self.gps is not None else None
        return statustext.OperatorState(
            camera=camera,
            vo_state=p.vo_state,
            vo_resets=p.vo_resets,
            reset_counter=s.last_reset_counter if s.published else None,
            scale_ready=tracking and p.scale is not None,
            scale_sensors=p.sensors_used,
            attitude_ready=self._attitude_held.update(tracking and p.roll_deg is not None, t_s),
            autopilot_silent_s=(now - hb) * 1e-9 if hb else None,
            rangefinder_faults=frozenset(d.sensor_id for d in self.tfminis if d.last_error),
            dpose_armed=dpose_armed,
            dpose_locked=self._dpose_lock.update(dpose_used, t_s),
            armed=s.autopilot_armed,
            link_rival=self.link.rival_address(now),
            frame=(frame.state if frame else "own") if self.gps is not None else None,
            frame_agree_m=_finite(frame.agreement_m) if frame else None,
            frame_to_target_m=_finite(frame.to_target_m) if frame else None,
            lens=p.lens_brief,
        )

    def offer_start(self, version: str, preflight_warnings: Sequence[str]) -> None:
        """The start events (sent once the link has a peer)."""
        output = self.rt.config.service.output
        for event in statustext.start_events(version, output, list(preflight_warnings)):
            self.limiter.offer(event, self.rt.clock() * 1e-9)

    async def statustext_loop(self) -> None:
        """Every STATUSTEXT_PERIOD_S: the events between the last snapshot and this one go to
        the limiter; what it lets out is sent while the link has somebody to send to."""
        while not self.rt.stopping:
            now = self.rt.clock()
            cur = self.state(now)
            events = statustext.transitions(self._operator, cur)
            events += frame_events.transitions(self._operator, cur)
            for event in events:
                self.limiter.offer(event, now * 1e-9)
            self._operator = cur
            if self.link.connected:
                for severity, text in self.limiter.take(now * 1e-9):
                    self._send(severity, text)
            await self.rt.sleep(statustext.STATUSTEXT_PERIOD_S)

    def _send(self, severity: int, text: str) -> None:
        """One text on the link (in chunks sharing an id when it is longer than 50)."""
        self._text_id = self._text_id % 0xFFFF + 1
        for msg in messages.statustext(self.link.mav, severity, text, self._text_id):
            self.link.send(msg)
        self.rt.stats.statustexts.append((int(severity), text))
        level = LOG_LEVEL_OF_SEVERITY[min(max(int(severity), 0), 7)]
        self.worker.recorder.log_line(self.rt.clock() // 1000, text, level, "companion.statustext")

    def last_words(self, tasks: Sequence[asyncio.Task[None]]) -> None:
        """At exit: what is still pending, then why we stop (the first of ``tasks`` that
        failed, if any; beyond the limits: bounded)."""
        failed = [t for t in tasks if t.done() and not t.cancelled() and t.exception() is not None]
        error = None
        if failed:
            exc = failed[0].exception()
            error = f"{failed[0].get_name()} error ({type(exc).__name__})"
        now_s = self.rt.clock() * 1e-9
        self.limiter.offer(statustext.stop_event(error, self.rt.stats.autopilot_armed), now_s)
        for severity, text in self.limiter.drain(now_s):
            self._send(severity, text)


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None
