"""The GPS handover state machine through scripted flights (companion.frames.handover).

Each flight (tests/peers/gps_tracks.py) runs at 30 Hz with a GPS fix every 6th sample through
the real verdict (companion.frames.gnss.GnssMonitor): good fixes (3-D, eph 0.9 m, 10
satellites) or lost ones (fix 0). Our own track drifts 2 cm/s north while the GPS is lost, as
a VO does. The output is our position through the applied alignment; between two outputs it
may move by at most slew_rate_m_s / 30 plus our own motion.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
from peers.gps_tracks import GPS_EVERY, TRUE_ALIGNMENT, Path, fly, hover, lawnmower

from companion.frames.alignment import FrameAlignment, wrap_rad
from companion.frames.gnss import GnssMonitor, GpsFix
from companion.frames.handover import (
    Handover,
    HandoverInput,
    HandoverOptions,
    HandoverOutput,
    slew,
)

RATE_M_S = HandoverOptions().slew_rate_m_s
RATE_RAD_S = HandoverOptions().slew_rate_rad_s
LOSS_S, RETURN_S, DRIFT_M_S = 60.0, 100.0, 0.02


@dataclass(frozen=True, slots=True)
class Run:
    """What one flight gave: per sample, our position, the output and the step's result."""

    time_s: np.ndarray
    ours: np.ndarray
    truth_ref: np.ndarray  # where the output should be: the true path in the autopilot's frame
    out: np.ndarray
    steps: list[HandoverOutput]

    def states(self) -> list[str]:
        """The states in order, each once per stretch."""
        seen = [s.state for s in self.steps]
        return [s for i, s in enumerate(seen) if i == 0 or seen[i - 1] != s]

    def first(self, state: str, after_s: float = 0.0) -> int:
        return next(
            i for i, s in enumerate(self.steps) if s.state == state and self.time_s[i] >= after_s
        )


def fly_handover(
    path: Path,
    gps_good: Callable[[float], bool | None],
    seed: int = 0,
    truth: FrameAlignment = TRUE_ALIGNMENT,
    gps_error: Callable[[float], np.ndarray] | None = None,
    may_jump_first: bool = True,
    drifts: bool = True,
    opts: HandoverOptions | None = None,
) -> Run:
    """``gps_good(t)``: True a good fix, False a lost one (fix 0), None no message at all;
    our track drifts from LOSS_S to RETURN_S (``drifts``); ``may_jump_first``: nothing is
    sent before the first alignment (the vehicle on the ground at boot), so it applies at once."""
    flight = fly(path, seed, truth=truth)
    monitor, machine = GnssMonitor(), Handover(opts)
    t_s = path.time_us * 1e-6
    ours, outs, steps = [], [], []
    ever_aligned = False
    for k, t_us in enumerate(path.time_us):
        state = gps_good(t_s[k])
        drift = DRIFT_M_S * min(max(t_s[k] - LOSS_S, 0.0), RETURN_S - LOSS_S) if drifts else 0.0
        p = flight.ours_ned_m[k] + np.array([drift, 0.0, 0.0])
        ref = None
        if k % GPS_EVERY == 0 and state is not None:
            fix = GpsFix(int(t_us), 3 if state else 0, 0.0, 0.0, 0.0, 0.9 if state else 99.0, 10)
            verdict = monitor.update(fix)
            if state:
                ref = flight.ref_ned_m[k] + (gps_error(t_s[k]) if gps_error else 0.0)
        else:
            verdict = monitor.at(int(t_us))
        step = machine.step(
            HandoverInput(
                int(t_us),
                p,
                float(flight.our_yaw_rad[k]),
                verdict.good,
                verdict.bad_since_us,
                ref,
                float(flight.ref_yaw_rad[k]) if ref is not None else math.nan,
                may_jump=may_jump_first and not ever_aligned,
            )
        )
        ever_aligned = ever_aligned or step.state == "aligned"
        ours.append(p)
        outs.append(step.applied.apply_points(p))
        steps.append(step)
    return Run(t_s, np.array(ours), truth.apply_points(path.position_ned_m), np.array(outs), steps)


def long_flight() -> Path:
    return lawnmower(legs=12)  # 147 s


def _step_excess(run: Run, start: int) -> np.ndarray:
    """Per step after ``start``: |output step| - (rate / 30 + |our step|) (<= 0: within)."""
    d_out = np.linalg.norm(np.diff(run.out[start:], axis=0), axis=1)
    d_ours = np.linalg.norm(np.diff(run.ours[start:], axis=0), axis=1)
    dt = np.diff(run.time_s[start:])
    result: np.ndarray = d_out - (RATE_M_S * dt + d_ours)
    return result


def test_a_loss_and_a_return_never_step_faster_than_the_slew_allows() -> None:
    drift_start = LOSS_S - 2.0

    def gps_error(t: float) -> np.ndarray:
        """The receiver drifts 2 m in the 2 s before it loses its fix, still saying 3-D."""
        ramp = min(1.0, max(0.0, (t - drift_start) / 2.0)) if t < LOSS_S else 0.0
        return np.array([1.4, 1.4, 0.0]) * ramp

    run = fly_handover(long_flight(), lambda t: not LOSS_S <= t < RETURN_S, gps_error=gps_error)
    assert run.states() == ["own", "aligning", "aligned", "held", "slewing", "aligned"]
    first_aligned = run.first("aligned")
    excess = _step_excess(run, first_aligned)
    assert excess.max() < 1e-9, f"step {excess.max():.4f} m over the limit"
    yaw = np.array([s.applied.yaw_rad for s in run.steps[first_aligned:]])
    dt = np.diff(run.time_s[first_aligned:])
    assert np.all(np.abs(np.diff(np.unwrap(yaw))) <= RATE_RAD_S * dt + 1e-12)

    held_at = run.first("held")
    held = run.steps[held_at]
    before = run.steps[held_at - 1]
    assert held.fit is not None and before.fit is not None
    # the refits just before the loss had taken the drifting fixes in; the held one has not
    assert before.fit.newest_us * 1e-6 > drift_start
    assert held.fit.newest_us * 1e-6 <= drift_start
    assert "before it degraded" in held.reason
    assert abs(math.degrees(wrap_rad(held.target.yaw_rad - TRUE_ALIGNMENT.yaw_rad))) < 1.0
    p = run.ours[held_at]
    assert np.linalg.norm(held.target.apply_points(p) - TRUE_ALIGNMENT.apply_points(p)) < 0.2
    assert math.isnan(held.agreement_m)
    # through the denial the output is our drifting track through the held alignment
    end_of_denial = run.first("held") + int((RETURN_S - LOSS_S - 1.0) * 30)
    denied = run.steps[end_of_denial]
    assert denied.state == "held"
    np.testing.assert_allclose(denied.applied.translation_ned_m, held.target.translation_ned_m)
    error_denied = np.linalg.norm(run.out[end_of_denial] - run.truth_ref[end_of_denial])
    assert 0.5 < error_denied < 1.2  # our 0.8 m of drift (plus the held fit's error)

    # after the return: verified, slewed at the limit, ending on the new alignment
    slew_at = run.first("slewing", after_s=RETURN_S)
    assert run.time_s[slew_at] >= RETURN_S + HandoverOptions().min_window_s - 0.5  # verified
    done = run.first("aligned", after_s=RETURN_S)
    assert run.steps[done].to_target_m < 1e-6  # the slew ends on the new alignment
    assert "verifying" in run.steps[slew_at - 1].reason
    gap = run.steps[slew_at].to_target_m
    assert 0.5 < gap < 1.5
    assert run.time_s[done] - run.time_s[slew_at] >= gap / RATE_M_S - 1.0
    final = run.steps[-1]
    assert final.state == "aligned" and final.fit is not None
    assert final.to_target_m < 0.02
    tail = slice(done, None)
    err = np.linalg.norm(run.out[tail] - run.truth_ref[tail], axis=1)
    assert err.mean() < 0.3  # back on the autopilot's frame, within the GPS noise
    assert 0.3 < final.agreement_m < 0.8


def test_the_held_alignment_is_the_one_a_flight_without_the_drift_holds() -> None:
    """The held alignment at the vehicle, with and without the receiver's 2 m of drift in the
    2 s before the loss: the same to the last bit with the 3 s hold-back; without it
    (hold_back_s = 0) the fit of 1 s before the loss holds, and the drift leaks in (~3 cm
    through a 20 s window: 5 of its 100 fixes)."""

    def gps_error(t: float) -> np.ndarray:
        ramp = min(1.0, max(0.0, (t - (LOSS_S - 2.0)) / 2.0)) if t < LOSS_S else 0.0
        return np.array([1.4, 1.4, 0.0]) * ramp

    def held_output(opts: HandoverOptions, drifting: bool) -> np.ndarray:
        run = fly_handover(
            long_flight(),
            lambda t: not LOSS_S <= t < RETURN_S,
            gps_error=gps_error if drifting else None,
            opts=opts,
        )
        at = run.first("held")
        result: np.ndarray = run.steps[at].target.apply_points(run.ours[at])
        return result

    kept = HandoverOptions()
    assert np.array_equal(held_output(kept, True), held_output(kept, False))
    none = HandoverOptions(hold_back_s=0.0)
    leak = np.linalg.norm(held_output(none, True) - held_output(none, False))
    assert 0.02 < leak < 0.1


def test_gps_appearing_mid_flight_slews_from_our_own_frame() -> None:
    """An indoor start: no GPS message for 20 s, then a good one: our frame (1.5 deg and
    (1, -0.5, 0.2) m from the autopilot's) is slewed onto it, never faster than the limit."""
    truth = FrameAlignment(math.radians(1.5), np.array([1.0, -0.5, 0.2]))
    run = fly_handover(
        lawnmower(legs=8),
        lambda t: True if t >= 20.0 else None,
        truth=truth,
        may_jump_first=False,
        drifts=False,
    )
    assert run.states() == ["own", "aligning", "slewing", "aligned"]
    assert run.time_s[run.first("aligning")] >= 20.0
    assert _step_excess(run, 0).max() < 1e-9
    slew_at, done = run.first("slewing"), run.first("aligned")
    gap = run.steps[slew_at].to_target_m
    assert gap > 0.5 and run.time_s[done] - run.time_s[slew_at] >= gap / RATE_M_S - 0.5
    tail = slice(done, None)
    assert np.linalg.norm(run.out[tail] - run.truth_ref[tail], axis=1).mean() < 0.3
    before = np.linalg.norm(run.out[:slew_at] - run.truth_ref[:slew_at], axis=1).mean()
    assert before > 0.5  # our own frame, as sent before the GPS came


def test_a_return_far_from_the_held_alignment_is_refused() -> None:
    """The receiver's first fixes after the outage 300 m off (the ArduPilot report in the
    research): the handover stays held and says why."""

    def bad_return(t: float) -> np.ndarray:
        return np.array([300.0, 0.0, 0.0]) if t >= RETURN_S else np.zeros(3)

    run = fly_handover(long_flight(), lambda t: not LOSS_S <= t < RETURN_S, gps_error=bad_return)
    assert run.states() == ["own", "aligning", "aligned", "held"]
    found = re.search(r"GPS back, but ([0-9.]+) m from the held alignment", run.steps[-1].reason)
    assert found is not None and "refused" in run.steps[-1].reason
    assert float(found.group(1)) == pytest.approx(300.0, abs=2.0)
    held = run.steps[run.first("held")].target
    assert np.allclose(run.steps[-1].applied.translation_ned_m, held.translation_ned_m)


def test_a_hover_aligns_on_the_headings() -> None:
    run = fly_handover(hover(30.0), lambda t: True)
    assert run.states() == ["own", "aligning", "aligned"]
    fit = run.steps[-1].fit
    assert fit is not None and fit.yaw_source == "attitude"
    assert abs(math.degrees(wrap_rad(fit.alignment.yaw_rad - TRUE_ALIGNMENT.yaw_rad))) < 1.0
    assert np.linalg.norm(run.out[-1] - run.truth_ref[-1]) < 0.4


def test_a_loss_before_any_alignment_returns_to_our_frame() -> None:
    run = fly_handover(lawnmower(legs=3), lambda t: t < 6.0, may_jump_first=False, drifts=False)
    assert run.states() == ["own", "aligning", "own"]
    assert "before an alignment" in run.steps[-1].reason
    assert all(s.applied.yaw_rad == 0.0 for s in run.steps)
    assert not np.any([s.applied.translation_ned_m for s in run.steps])


@pytest.mark.parametrize("yaw_deg", [-170.0, 3.0, 90.0])
def test_slew_turns_about_the_vehicle_and_moves_its_output_at_the_rate(yaw_deg: float) -> None:
    p = np.array([30.0, -20.0, -5.0])
    start = FrameAlignment(math.radians(yaw_deg), np.array([1.0, 2.0, 0.0]))
    target = FrameAlignment(math.radians(yaw_deg + 10.0), np.array([4.0, -2.0, 1.0]))
    a = start
    for _ in range(30):
        b = slew(a, target, p, 1 / 30, 0.1, math.radians(0.5))
        assert np.linalg.norm(b.apply_points(p) - a.apply_points(p)) <= 0.1 / 30 + 1e-12
        assert abs(wrap_rad(b.yaw_rad - a.yaw_rad)) == pytest.approx(math.radians(0.5) / 30)
        a = b
    turned = slew(start, FrameAlignment(target.yaw_rad, start.translation_ned_m), p, 1.0, 0.0, 1.0)
    np.testing.assert_allclose(turned.apply_points(p), start.apply_points(p), atol=1e-9)
    assert turned.yaw_rad == pytest.approx(target.yaw_rad)
    reached = slew(start, target, p, 1e3, 1.0, 1.0)
    assert reached.yaw_rad == pytest.approx(target.yaw_rad)
    np.testing.assert_allclose(reached.translation_ned_m, target.translation_ned_m, atol=1e-9)


def test_a_reanchor_carries_every_alignment_onto_the_new_frame() -> None:
    from companion.frames.handover import compose

    h = Handover()
    h.state = "held"
    h.applied = FrameAlignment(0.3, np.array([1.0, 2.0, 3.0]))
    h.target = FrameAlignment(0.35, np.array([1.5, 2.0, 3.0]))
    h.pairs.append((0, np.zeros(3), np.zeros(3), 0.0, 0.0, 0))
    new_to_old = FrameAlignment(-1.1, np.array([7.0, -4.0, 0.5]))
    old_applied, old_target = h.applied, h.target
    h.reanchor(new_to_old)
    p_new = np.array([[3.0, -2.0, -5.0], [-40.0, 10.0, -2.0]])
    p_old = new_to_old.apply_points(p_new)
    assert np.allclose(h.applied.apply_points(p_new), old_applied.apply_points(p_old), atol=1e-12)
    assert np.allclose(h.target.apply_points(p_new), old_target.apply_points(p_old), atol=1e-12)
    assert h.state == "held" and not h.pairs and "carried over" in h.reason
    # composing with the inverse gives the identity
    back = compose(new_to_old, new_to_old.inverse())
    assert abs(back.yaw_rad) < 1e-12 and np.allclose(back.translation_ned_m, 0.0, atol=1e-12)


def test_a_carried_lag_moves_the_output_at_once_and_slews_out_at_the_rate() -> None:
    """At a loss the output takes on the autopilot's lag (0.4 m here) in one step; the held
    target is unchanged, so every later step returns towards it at the slew rate, and after
    |lag| / rate the output is where it would have been without the carry."""
    h = Handover()
    h.state = "held"
    h.applied = h.target = FrameAlignment(0.7, np.array([2.0, -1.0, 0.0]))
    p = np.array([10.0, 5.0, -5.0])
    lag = np.array([-0.32, 0.24, 0.0])
    h.step(HandoverInput(0, p, 0.0, gps_good=False, gps_bad_since_us=0))  # the loss's step
    before = h.applied.apply_points(p)
    assert h.carry(lag, p) == pytest.approx(0.4)
    assert np.allclose(h.applied.apply_points(p) - before, lag, atol=1e-12)
    assert "0.40 m lag" in h.reason
    out = [h.applied.apply_points(p)]
    for k in range(1, 6 * 30):
        s = h.step(HandoverInput(k * 33_333, p, 0.0, gps_good=False, gps_bad_since_us=0))
        out.append(s.applied.apply_points(p))
    steps = np.linalg.norm(np.diff(out, axis=0), axis=1)
    assert steps.max() <= RATE_M_S * 0.033334 + 1e-12
    arrived = int(np.argmax(steps < 1e-12))  # 0.4 m at 0.1 m/s: 4 s
    assert arrived / 30 == pytest.approx(4.0, abs=0.1)
    assert np.allclose(out[-1], before, atol=1e-9)
