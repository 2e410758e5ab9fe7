"""In which frame our output goes while GPS comes and goes: a time-driven state machine (pure).

States (``HandoverOutput.state``):

* ``own``: no good GPS yet: our own frame (the identity, or the alignment we had).
* ``aligning``: GPS good, pairs (ours, the GPS position in the autopilot's local NED) being
  collected; after ``min_window_s`` of them a fit (:func:`companion.frames.alignment.fit_track`)
  that agrees within ``max_rms_m`` becomes the target and the output slews onto it.
* ``slewing``: the output moving onto the target alignment at a bounded rate; ``aligned`` once
  it is there.
* ``aligned``: the output in the autopilot's frame; refitted every ``refit_interval_s`` over the
  last ``window_s``, the output following the refits at the same bounded rate.
* ``held``: GPS lost: the alignment frozen from before the GPS degraded (the newest fit whose
  pairs all precede the first bad GPS sample by ``hold_back_s``: a receiver drifts before it
  says so), kept through the denial. When the GPS is good again, pairs are collected afresh;
  once ``min_window_s`` of them agree (and the new alignment lies within
  ``max_return_offset_m`` of the held one at the vehicle: a far-off first fix is refused), it
  becomes the target: ``slewing``, then ``aligned``. At the loss the caller may carry the
  autopilot's own lag into the output (:meth:`Handover.carry`): the slew takes it out again.

The rate limit (research: PX4 pulls ~0.1 m/s onto GPS by itself; ArduPilot resets at the
switch unless the frames agree): each step the applied alignment's yaw moves at most
``slew_rate_rad_s`` x dt towards the target's, and the output of our current position at most
``slew_rate_m_s`` x dt (the turn is about the vehicle, so it moves nothing). So between two
outputs |out_k - out_k-1| <= slew_rate_m_s dt + |p_k - p_k-1| (p: our position).

Inputs (:class:`HandoverInput`) are plain samples on our clock: our position (NED, our frame
[m]) and yaw [rad] at ``time_us``; the GPS verdict (:mod:`companion.frames.gnss`); when a fix
is at hand, the reference position at the same instant (the caller interpolates ours to the
fix's stamp: :func:`companion.frames.alignment.match_pairs`) and the autopilot's yaw.
A reset of our own frame (a new ``reset_counter``): the caller says how the new frame lies in
the old (:meth:`Handover.reanchor`, from our last pose before and first after it); every
alignment in hand (applied, target, held) is carried over onto the new frame so that the output
goes on where it was, and the pairs and fits of the old frame are dropped.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from companion.frames.alignment import (
    FitOptions,
    FrameAlignment,
    PairWindow,
    TrackFit,
    fit_track,
    wrap_rad,
)
from companion.geometry import so3
from companion.types import F64

State = Literal["own", "aligning", "aligned", "held", "slewing"]


@dataclass(frozen=True, slots=True)
class HandoverOptions:
    """Windows [s], thresholds [m], rates [m/s, rad/s] (module docstring)."""

    window_s: float = 20.0
    min_window_s: float = 8.0
    min_pairs: int = 20
    refit_interval_s: float = 1.0
    max_rms_m: float = 1.0
    hold_back_s: float = 3.0
    slew_rate_m_s: float = 0.1
    slew_rate_rad_s: float = math.radians(0.5)
    max_return_offset_m: float = 30.0
    fit: FitOptions = field(default_factory=FitOptions)

    @staticmethod
    def from_gps_options(g: Any) -> HandoverOptions:
        """[gps]'s tunable thresholds (companion.service_options.GpsOptions) as taken here."""
        return HandoverOptions(
            window_s=g.window_s,
            min_window_s=g.min_window_s,
            max_rms_m=g.max_rms_m,
            slew_rate_m_s=g.slew_rate_m_s,
            slew_rate_rad_s=math.radians(g.slew_rate_deg_s),
            max_return_offset_m=g.max_return_offset_m,
        )


@dataclass(frozen=True, slots=True)
class HandoverInput:
    """One step: our pose at ``time_us``, the GPS verdict, and a reference fix when one is at
    hand. our_position_ned_m: (3,) [m]; ref_position_ned_m: (3,) [m] in the autopilot's local
    NED at the same instant, or None; yaws [rad] (ref NaN: none); gps_bad_since_us: the
    verdict's first bad sample of the current bad run (None: the newest sample is good);
    may_jump: nothing has been sent yet, so the first alignment is applied at once."""

    time_us: int
    our_position_ned_m: F64
    our_yaw_rad: float
    gps_good: bool
    gps_bad_since_us: int | None = None
    ref_position_ned_m: F64 | None = None
    ref_yaw_rad: float = math.nan
    reset_counter: int = 0
    may_jump: bool = False


@dataclass(frozen=True, slots=True)
class HandoverOutput:
    """applied: the alignment to apply to our pose now; target: where it is heading;
    agreement_m: the residual RMS of the fit in use while GPS is good (NaN otherwise);
    to_target_m: how far the output at the vehicle still has to move; fit_age_s: since the
    newest pair of the fit in use (NaN: none); reason: the latest transition, in words."""

    state: State
    applied: FrameAlignment
    target: FrameAlignment
    agreement_m: float
    to_target_m: float
    fit: TrackFit | None
    fit_age_s: float
    reason: str


def slew(
    applied: FrameAlignment,
    target: FrameAlignment,
    position_ned_m: F64,
    dt_s: float,
    rate_m_s: float,
    rate_rad_s: float,
) -> FrameAlignment:
    """``applied`` moved towards ``target``: the yaw by at most rate_rad_s dt (a turn about
    ``position_ned_m``), the output of ``position_ned_m`` by at most rate_m_s dt."""
    d_yaw = wrap_rad(target.yaw_rad - applied.yaw_rad)
    step = max(-rate_rad_s * dt_s, min(rate_rad_s * dt_s, d_yaw))
    yaw = applied.yaw_rad + step
    here = applied.apply_points(position_ned_m)
    d = target.apply_points(position_ned_m) - here
    dist, limit = float(np.linalg.norm(d)), rate_m_s * dt_s
    if dist > limit:
        d = d * (limit / dist)
    out = here + d
    return FrameAlignment(wrap_rad(yaw), out - so3.rot_z(yaw) @ position_ned_m)


def compose(first: FrameAlignment, then: FrameAlignment) -> FrameAlignment:
    """``then`` after ``first``: p -> then(first(p))."""
    R = so3.rot_z(then.yaw_rad)
    return FrameAlignment(
        wrap_rad(first.yaw_rad + then.yaw_rad),
        R @ first.translation_ned_m + then.translation_ned_m,
    )


class Handover:
    """The state machine; :meth:`step` once per output sample, in time order."""

    def __init__(self, opts: HandoverOptions | None = None) -> None:
        self.opts = opts or HandoverOptions()
        self.state: State = "own"
        self.applied = FrameAlignment.identity()
        self.target = FrameAlignment.identity()
        self.fit: TrackFit | None = None  # the fit in use
        self.fits: deque[TrackFit] = deque()  # recent fits, for the held one
        self.pairs: deque[tuple[int, F64, F64, float, float, int]] = deque()
        self.last_us: int | None = None
        self.last_fit_us: int | None = None
        self.reason = "no GPS yet: our own frame"

    def step(self, s: HandoverInput) -> HandoverOutput:
        """Advance to ``s.time_us`` and return what to apply."""
        dt_s = 0.0 if self.last_us is None else max(0.0, (s.time_us - self.last_us) * 1e-6)
        self.last_us = s.time_us
        self._collect(s)
        self._transition(s)
        o = self.opts
        self.applied = slew(
            self.applied,
            self.target,
            s.our_position_ned_m,
            dt_s,
            o.slew_rate_m_s,
            o.slew_rate_rad_s,
        )
        gap = self._to_target(s.our_position_ned_m)
        if self.state == "slewing" and gap[0] < 1e-6 and abs(gap[1]) < 1e-9:
            self.state, self.reason = "aligned", "slew done: in the autopilot's frame"
        gps_fit = self.fit is not None and self.state in ("aligning", "aligned", "slewing")
        return HandoverOutput(
            state=self.state,
            applied=self.applied,
            target=self.target,
            agreement_m=self.fit.residual_rms_m if gps_fit and self.fit else math.nan,
            to_target_m=gap[0],
            fit=self.fit,
            fit_age_s=(s.time_us - self.fit.newest_us) * 1e-6 if self.fit else math.nan,
            reason=self.reason,
        )

    def reanchor(self, new_to_old: FrameAlignment) -> None:
        """Our frame was reset: ``new_to_old`` maps a point of the new frame into the old one.
        The applied and target alignments (the held one too) now map the new frame, so the
        output is continuous; the old frame's pairs and fits are dropped (a refit waits for
        ``min_window_s`` of the new frame's pairs; a loss meanwhile holds the applied one)."""
        self.applied = compose(new_to_old, self.applied)
        self.target = compose(new_to_old, self.target)
        self.pairs.clear()
        self.fits.clear()
        self.last_fit_us = None
        if self.state in ("aligned", "slewing", "held"):
            self.reason = f"our frame reset: the {self.state} alignment carried over onto it"

    def carry(self, offset_ned_m: F64, position_ned_m: F64) -> float:
        """Our output moved by ``offset_ned_m`` (3,) [m] now (the autopilot's lag at a GPS loss:
        :mod:`companion.frames.carry`); each later :meth:`step` takes it out again at
        ``slew_rate_m_s`` on the way to the target. Returns how far the output at
        ``position_ned_m`` now has to move [m]."""
        offset = np.asarray(offset_ned_m, np.float64)
        self.applied = FrameAlignment(self.applied.yaw_rad, self.applied.translation_ned_m + offset)
        self.reason += f"; carrying the autopilot's {float(np.linalg.norm(offset)):.2f} m lag"
        return self._to_target(position_ned_m)[0]

    def _to_target(self, position_ned_m: F64) -> tuple[float, float]:
        d = self.target.apply_points(position_ned_m) - self.applied.apply_points(position_ned_m)
        return float(np.linalg.norm(d)), wrap_rad(self.target.yaw_rad - self.applied.yaw_rad)

    def _collect(self, s: HandoverInput) -> None:
        """Keep a pair when a fix is at hand and the newest GPS sample is good."""
        if s.ref_position_ned_m is not None and s.gps_bad_since_us is None:
            self.pairs.append(
                (
                    s.time_us,
                    np.asarray(s.our_position_ned_m, np.float64),
                    np.asarray(s.ref_position_ned_m, np.float64),
                    s.our_yaw_rad,
                    s.ref_yaw_rad,
                    s.reset_counter,
                )
            )
        while self.pairs and s.time_us - self.pairs[0][0] > self.opts.window_s * 1e6:
            self.pairs.popleft()
        keep_us = (self.opts.window_s + self.opts.hold_back_s) * 1e6
        while self.fits and s.time_us - self.fits[0].newest_us > keep_us:
            self.fits.popleft()

    def _window(self) -> PairWindow:
        p = list(self.pairs)
        return PairWindow(
            np.array([q[0] for q in p], dtype=np.int64),
            np.array([q[1] for q in p]).reshape(-1, 3),
            np.array([q[2] for q in p]).reshape(-1, 3),
            np.array([q[3] for q in p], dtype=np.float64),
            np.array([q[4] for q in p], dtype=np.float64),
            np.array([q[5] for q in p], dtype=np.int64),
        ).latest_epoch()

    def _refit(self, now_us: int) -> TrackFit | None:
        """A fit over the window when it is due and the window is long enough, else None."""
        o = self.opts
        if self.last_fit_us is not None and now_us - self.last_fit_us < o.refit_interval_s * 1e6:
            return None
        w = self._window()
        if len(w) < o.min_pairs or (w.time_us[-1] - w.time_us[0]) < o.min_window_s * 1e6:
            return None
        self.last_fit_us = now_us
        fit = fit_track(w, opts=o.fit)
        if fit is None:
            self.reason = "GPS good, but our track gives no yaw yet (no travel, no headings)"
            return None
        if fit.residual_rms_m > o.max_rms_m:
            self.reason = (
                f"GPS and our track disagree by {fit.residual_rms_m:.2f} m RMS "
                f"(> {o.max_rms_m:g} m): no alignment taken"
            )
            return None
        self.fits.append(fit)
        return fit

    def _transition(self, s: HandoverInput) -> None:
        if self.state in ("aligning", "aligned", "slewing") and not s.gps_good:
            self._lose(s)
            return
        if self.state == "own" and s.gps_good:
            self.state, self.reason = "aligning", "GPS good: collecting pairs"
            self.last_fit_us = None
        if self.state == "held" and not s.gps_good:
            if s.gps_bad_since_us is not None:
                self.pairs.clear()  # a return that did not last: start again
                self.last_fit_us = None
            return
        if self.state == "held" and self.reason.startswith("GPS lost"):
            self.reason = "GPS back: verifying it against the held alignment"
        fit = self._refit(s.time_us)
        if fit is None:
            return
        if self.state == "held":
            if not self._return_plausible(fit, s.our_position_ned_m):
                return
            self.state, self.reason = "slewing", "GPS back and verified: slewing onto it"
        elif self.state == "aligning":
            if s.may_jump:
                self.applied = fit.alignment
                self.state, self.reason = "aligned", "aligned before the first output"
            else:
                self.state, self.reason = "slewing", "first alignment: slewing onto it"
        self.fit, self.target = fit, fit.alignment

    def _lose(self, s: HandoverInput) -> None:
        """GPS lost: back to our own frame before any alignment, else hold one."""
        bad_us = s.gps_bad_since_us if s.gps_bad_since_us is not None else s.time_us
        self.pairs.clear()
        self.last_fit_us = None
        if self.state == "aligning":
            self.state, self.reason = "own", "GPS lost before an alignment: our own frame"
            return
        before = bad_us - int(self.opts.hold_back_s * 1e6)
        older = [f for f in self.fits if f.newest_us <= before]
        self.state = "held"
        if older:
            self.fit, self.target = older[-1], older[-1].alignment
            self.reason = (
                f"GPS lost: holding the alignment of {(bad_us - older[-1].newest_us) * 1e-6:.1f} s "
                "before it degraded"
            )
        else:
            self.fit, self.target = None, self.applied
            self.reason = "GPS lost: no alignment old enough: holding the one applied"
        self.fits.clear()

    def _return_plausible(self, fit: TrackFit, position_ned_m: F64) -> bool:
        """The new alignment's output at the vehicle within max_return_offset_m of the held."""
        held = self.target.apply_points(position_ned_m)
        offset = float(np.linalg.norm(fit.alignment.apply_points(position_ned_m) - held))
        if offset > self.opts.max_return_offset_m:
            self.reason = (
                f"GPS back, but {offset:.1f} m from the held alignment at the vehicle "
                f"(> {self.opts.max_return_offset_m:g} m): refused, still held"
            )
            self.fits.pop()
            return False
        return True
