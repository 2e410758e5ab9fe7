"""Our output in the autopilot's GPS-aided frame ([gps] align; docs/gps.md): the service's
owner of the :class:`companion.frames.handover.Handover` state machine.

Inputs (on the event loop): GPS_RAW_INT and GPS_GLOBAL_ORIGIN (``on_gps_raw``, ``on_origin``;
a fix stamped at its reception on our clock [us]: ArduPilot's time_usec is GPS time, not its
boot clock), the autopilot's ATTITUDE yaw [rad] (``on_attitude``), and every pose we are about
to publish, in our own frame (``align``). A fix becomes the GPS position in the autopilot's
local NED about its origin (its own projection: PX4's or ArduPilot's, by the HEARTBEAT), is
held until a pose after it arrives, and is paired with our position interpolated between the
two poses around its stamp; a fix or origin out of range is counted and dropped. GPS altitude
is used only with [gps] align_height: otherwise the pair's height is ours, so the alignment
moves nothing in z (research section 4: the height stays the autopilot's height reference).

Output: ``align(pose)``: the pose in the autopilot's frame (position Rz p + t, attitude and
velocity turned by the yaw, the covariance's position block turned: the variances along the
axes of the autopilot's frame; roll, pitch, yaw variances unchanged), with the reset counter
stepped once when the first alignment is applied at once (the autopilot disarmed: a jump with
a new counter, which EKF2 / EKF3 re-anchor on; armed, it is slewed onto at the bounded rate).
A reset of our own frame (the pipeline's counter changed) re-anchors the alignment
(``Handover.reanchor``) so that the output goes on where it was: the new frame's heading
against the old one from the autopilot's yaw at the two poses, its origin where the old frame's
last pose and velocity put the vehicle. The GPS loss and the end of the slew after a return
start the autopilot's actions (``gps_actions``). At a loss with PX4 told, EKF2's lag behind our
output is carried into the output first (``gps_lag``).
``status()``: the status's ``frame`` section.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.frames.alignment import FrameAlignment, apply, pose_yaw, wrap_rad
from companion.frames.gnss import (
    GlobalOrigin,
    GnssMonitor,
    GnssOptions,
    GnssVerdict,
    GpsFix,
    Projection,
    plausible_position,
    to_local_ned,
)
from companion.frames.handover import Handover, HandoverInput, HandoverOptions, HandoverOutput
from companion.geometry import so3
from companion.service.gps_actions import GpsActions
from companion.service.gps_lag import CARRY_SWITCH_DELAY_S, LagCarry
from companion.service.runtime import AutopilotKind, Runtime
from companion.types import F64, PoseEstimate

log = logging.getLogger("companion.service")

MAX_PAIR_GAP_US = 200_000  # a fix between two of our poses further apart makes no pair
MAX_YAW_AGE_US = 100_000  # the autopilot's yaw this close to a fix's stamp, else none
MAX_REANCHOR_GAP_US = 2_000_000  # our velocity carries the old frame over a gap this long
PENDING_FIXES = 64  # fixes waiting for a pose after them (poses stopped: the oldest go)
ORIGIN_ASK_US = 2_000_000  # GPS_GLOBAL_ORIGIN asked for this often until it arrives
MAV_CMD_REQUEST_MESSAGE = 512
NO_GPS_AT_START_US = 5_000_000  # ArduPilot: no good GPS this long after our first pose


@dataclass(frozen=True, slots=True)
class OurSample:
    """One of our poses before alignment: time_us, position NED (3,) [m], yaw [rad], velocity
    NED (3,) [m/s] (NaN: unknown), the pipeline's reset counter."""

    time_us: int
    position_ned_m: F64
    yaw_rad: float
    velocity_ned_m_s: F64
    reset_counter: int


class GpsFrame:
    """GPS in, our pose in the autopilot's frame out (module docstring)."""

    def __init__(self, rt: Runtime, link: Any) -> None:
        g = rt.config.gps
        self.rt = rt
        self.monitor = GnssMonitor(
            GnssOptions(
                max_eph_m=g.max_eph_m, min_satellites=g.min_satellites, good_after_s=g.good_after_s
            )
        )
        self.handover = Handover(HandoverOptions.from_gps_options(g))
        self.link = link
        self.actions = GpsActions(rt, link)
        self._origin_asked_us = -ORIGIN_ASK_US
        self.origin_requests = 0
        self.origin: GlobalOrigin | None = None
        self.pending: deque[tuple[int, F64]] = deque(maxlen=PENDING_FIXES)
        self.yaws: deque[tuple[int, float]] = deque(maxlen=256)  # autopilot's (time_us, yaw)
        self.last: OurSample | None = None
        self.out: HandoverOutput | None = None
        self.verdict: GnssVerdict | None = None
        self.jumps = 0  # first alignments applied at once (each steps the reset counter)
        self.jumped = False  # the last pose aligned was the first of such a jump
        self.fixes = self.dropped = self.pairs = self.unpaired = self.reanchors = 0
        self._returning = False  # held -> slewing: the return's actions wait for "aligned"
        self._first_pose_us: int | None = None
        self.told_no_gps = False  # ArduPilot told to use ours: no good GPS since our start
        self.lag = LagCarry(g.px4_loss_carry)  # EKF2's lag, carried at a loss (PX4)

    # ------------------------------------------------------------------ in
    def projection(self) -> Projection:
        """The autopilot's own projection (ArduPilot's when its HEARTBEAT says so)."""
        return "ardupilot" if self.rt.stats.autopilot_kind is AutopilotKind.ARDUPILOT else "px4"

    def on_origin(self, latitude: int, longitude: int, altitude: int) -> None:
        """GPS_GLOBAL_ORIGIN (degE7, degE7, mm AMSL); out of range: dropped."""
        o = GlobalOrigin.from_message(latitude, longitude, altitude)
        if not plausible_position(o.lat_deg, o.lon_deg, o.alt_m):
            self.dropped += 1
            return
        if self.origin is not None and o != self.origin:
            self.rt.warn("GPS: the autopilot's EKF origin moved; fixes from now on about the new")
        self.origin = o

    def on_gps_raw(self, msg: Any, time_us: int) -> None:
        """GPS_RAW_INT received at ``time_us`` (our clock): the verdict, and the fix queued
        for pairing when good and the origin is known; a malformed one dropped."""
        try:
            fix = GpsFix.from_gps_raw_int(
                time_us,
                int(msg.fix_type),
                int(msg.lat),
                int(msg.lon),
                int(msg.alt),
                int(msg.eph),
                int(msg.satellites_visible),
            )
        except (TypeError, ValueError, OverflowError):
            self.dropped += 1
            return
        if not (0 <= fix.fix_type <= 8 and plausible_position(fix.lat_deg, fix.lon_deg, fix.alt_m)):
            self.dropped += 1
            return
        self.fixes += 1
        self.verdict = self.monitor.update(fix)
        if self.origin is None and time_us - self._origin_asked_us >= ORIGIN_ASK_US:
            self._ask_origin(time_us)
        if self.verdict.sample_good and self.origin is not None:
            ned = to_local_ned(self.origin, fix.lat_deg, fix.lon_deg, fix.alt_m, self.projection())
            self.pending.append((time_us, ned))

    def _ask_origin(self, time_us: int) -> None:
        """MAV_CMD_REQUEST_MESSAGE GPS_GLOBAL_ORIGIN: PX4 sends it when its origin changes,
        so one set before our rate request never comes by itself."""
        self._origin_asked_us = time_us
        self.origin_requests += 1
        mav, sysid = self.link.mav, self.rt.stats.autopilot_system_id
        self.link.send(
            mav.command_long_encode(sysid, 1, MAV_CMD_REQUEST_MESSAGE, 0, 49, 0, 0, 0, 0, 0, 0)
        )

    def on_attitude(self, time_us: int, yaw_rad: float) -> None:
        """The autopilot's heading [rad] at ``time_us`` (ATTITUDE, already checked)."""
        self.yaws.append((time_us, yaw_rad))

    def _yaw_at(self, time_us: int) -> float:
        """The autopilot's heading nearest ``time_us`` (NaN: none within MAX_YAW_AGE_US)."""
        best, best_dt = math.nan, MAX_YAW_AGE_US + 1
        for t, yaw in reversed(self.yaws):
            dt = abs(t - time_us)
            if dt < best_dt:
                best, best_dt = yaw, dt
            elif t < time_us:
                break
        return best

    # ------------------------------------------------------------------ out
    def align(self, pose: PoseEstimate) -> PoseEstimate:
        """``pose`` (our frame; the pipeline's reset counter) in the autopilot's frame now,
        with the reset counter stepped by the jumps so far."""
        cur = OurSample(
            pose.time_us,
            np.asarray(pose.position_ned_m, np.float64),
            pose_yaw(pose),
            np.asarray(pose.velocity_ned_m_s, np.float64),
            pose.reset_counter,
        )
        last = self.last
        if last is not None and cur.reset_counter != last.reset_counter:
            self._reanchor(last, cur)
            last = None
        verdict = self.verdict = self.monitor.at(cur.time_us)  # a silence too
        jumps = self.jumps
        while self.pending and self.pending[0][0] <= cur.time_us:
            t_fix, ned = self.pending.popleft()
            if last is None or t_fix < last.time_us or cur.time_us - last.time_us > MAX_PAIR_GAP_US:
                self.unpaired += 1
                continue
            a = (t_fix - last.time_us) / max(cur.time_us - last.time_us, 1)
            ours = last.position_ned_m + a * (cur.position_ned_m - last.position_ned_m)
            yaw = wrap_rad(last.yaw_rad + a * wrap_rad(cur.yaw_rad - last.yaw_rad))
            self.pairs += 1
            if not self.rt.config.gps.align_height:  # GPS altitude unused: z stays ours
                ned = np.array([ned[0], ned[1], ours[2]])
            self._step(t_fix, ours, yaw, verdict, cur.reset_counter, ned, self._yaw_at(t_fix))
        out = self._step(cur.time_us, cur.position_ned_m, cur.yaw_rad, verdict, cur.reset_counter)
        self._without_gps_at_start(cur.time_us, out.state, verdict.good)
        self.last = cur
        self.jumped = self.jumps != jumps
        aligned = apply(out.applied, pose)
        self.lag.on_output(cur.time_us, aligned.position_ned_m)
        self.actions.tick()  # a delayed action goes with the pose after it is due
        return dataclasses.replace(aligned, reset_counter=pose.reset_counter + self.jumps)

    def _step(
        self,
        time_us: int,
        ours: F64,
        yaw: float,
        verdict: GnssVerdict,
        reset_counter: int,
        ref: F64 | None = None,
        ref_yaw: float = math.nan,
    ) -> HandoverOutput:
        before = self.handover.state
        may_jump = before == "aligning" and not self.rt.stats.autopilot_armed
        out = self.handover.step(
            HandoverInput(
                time_us,
                ours,
                yaw,
                verdict.good,
                verdict.bad_since_us,
                ref,
                ref_yaw,
                reset_counter,
                may_jump,
            )
        )
        self.out = out
        if out.state != before:
            self._transition(before, out, time_us, ours)
        return self.out

    def _carry_lag(self, time_us: int, ours: F64) -> float:
        """At a loss: EKF2's lag carried into our output when PX4 is told (``gps_lag``);
        returns how long EKF2_GPS_CTRL 0 waits [s]."""
        if self.actions.target() != "px4":
            self.lag.carried_m = None
            return 0.0
        offset = self.lag.at_loss(time_us)
        if offset is None:
            return 0.0
        to_target_m = self.handover.carry(offset, ours)
        if self.out is not None:
            self.out = dataclasses.replace(
                self.out,
                applied=self.handover.applied,
                to_target_m=to_target_m,
                reason=self.handover.reason,
            )
        return CARRY_SWITCH_DELAY_S

    def _without_gps_at_start(self, time_us: int, state: str, gps_good: bool) -> None:
        """No good GPS NO_GPS_AT_START_US after our first pose (indoors): ArduPilot, whose set 1
        is GPS, is told to use ours (set 2) once, and set 1 follows the first alignment. PX4
        needs nothing: it fuses ours beside a GNSS that is not there, and GNSS once it is."""
        if self._first_pose_us is None:
            self._first_pose_us = time_us
        if (
            self.told_no_gps
            or state != "own"
            or gps_good
            or time_us - self._first_pose_us < NO_GPS_AT_START_US
            or self.actions.target() != "ardupilot"
        ):
            return
        self.told_no_gps = self._returning = True
        log.info("GPS frame: no GPS since our start: the autopilot is told to use ours")
        self.actions.on_loss()

    def _transition(self, before: str, out: HandoverOutput, time_us: int, ours: F64) -> None:
        """A new state: logged; the jump counted; the autopilot's actions started."""
        log.info("GPS frame: %s -> %s (%s)", before, out.state, out.reason)
        if before == "aligning" and out.state == "aligned":
            self.jumps += 1
        if out.state == "held":
            self._returning = False
            self.actions.on_loss(delay_s=self._carry_lag(time_us, ours))
        elif before == "held" and out.state == "slewing":
            self._returning = True
        elif before in ("slewing", "aligning") and out.state == "aligned" and self._returning:
            self._returning = False
            self.actions.on_return()

    def _reanchor(self, old: OurSample, new: OurSample) -> None:
        """Our frame was reset between ``old`` (the old frame's last pose) and ``new``: the
        new frame laid into the old (module docstring)."""
        gap_us = new.time_us - old.time_us
        d_yaw = wrap_rad(old.yaw_rad - new.yaw_rad)  # the vehicle kept its heading ...
        ap_old, ap_new = self._yaw_at(old.time_us), self._yaw_at(new.time_us)
        if math.isfinite(ap_old) and math.isfinite(ap_new):  # ... or turned as the autopilot saw
            d_yaw = wrap_rad(d_yaw + (ap_new - ap_old))
        here = old.position_ned_m
        if np.all(np.isfinite(old.velocity_ned_m_s)) and 0 < gap_us <= MAX_REANCHOR_GAP_US:
            here = here + old.velocity_ned_m_s * (gap_us * 1e-6)
        new_to_old = FrameAlignment(d_yaw, here - so3.rot_z(d_yaw) @ new.position_ned_m)
        self.handover.reanchor(new_to_old)
        self.reanchors += 1
        log.info(
            "GPS frame: our frame reset (counter %d): alignment carried over", new.reset_counter
        )

    # ------------------------------------------------------------------ status
    def status(self) -> dict[str, Any]:
        """The status's ``frame`` section: state, agreement [m], the alignment applied (yaw
        [deg], translation NED [m]), the fit's age [s], the GPS verdict, the actions."""
        out, v = self.out, self.verdict
        applied = out.applied if out is not None else FrameAlignment.identity()
        return {
            "enabled": True,
            "state": out.state if out is not None else "own",
            "agreement_m": _finite(out.agreement_m) if out is not None else None,
            "to_target_m": _finite(out.to_target_m) if out is not None else None,
            "yaw_deg": math.degrees(applied.yaw_rad),
            "translation_ned_m": [float(x) for x in applied.translation_ned_m],
            "age_s": _finite(out.fit_age_s) if out is not None else None,
            "reason": out.reason if out is not None else "no pose yet",
            "gps": {
                "good": bool(v.good) if v is not None else False,
                "reasons": list(v.reasons) if v is not None else ["no GPS sample yet"],
                "origin": self.origin is not None,
                "origin_requests": self.origin_requests,
                "fixes": self.fixes,
                "dropped": self.dropped,
                "pairs": self.pairs,
            },
            "reanchors": self.reanchors,
            "carried_m": self.lag.carried_m,
            "autopilot_positions_dropped": self.lag.dropped,
            "handover": self.actions.status(),
        }


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None
