"""MAVLink TIMESYNC on the companion side: answer the autopilot and estimate its clock.

Protocol (MAVLink common TIMESYNC, as PX4's Timesync.cpp uses it): a request carries tc1 = 0
and ts1 = the sender's clock [ns]; the answer carries tc1 = the answerer's clock [ns] and ts1
echoed. PX4 sends requests as a stream (10 Hz on an onboard link unless asked for another rate:
the service asks for ``service.px4_timesync_rate_hz``, 50 Hz) and converts our time_usec only
after its own filter has converged on ~500 of our answers, so :func:`reply_for` must be
answered at once.

We also keep our own estimate of the autopilot clock (its time_boot_ms / time_usec) so that
DISTANCE_SENSOR and ATTITUDE samples can be moved into the companion's monotonic clock. From our
own requests: round trip rtt = now - ts1 and offset = (ts1 + now) / 2 - tc1 (companion minus
autopilot, ns), assuming a symmetric path. Samples with an rtt above max_rtt_ns are ignored, and
so are samples much slower than the fast recent ones (their 20th percentile: a reply that
waited in a busy peer's socket buffer is asymmetric, and its offset is off by up to half its
round trip: the NTP practice of trusting the fastest exchanges).

The others feed a two-state tracker of the offset and its rate, the skew (a drifting crystal:
a few to a few hundred ppm; PX4 SITL's lockstep clock: up to 3 % slow on a slow host), whose
conversions extrapolate the offset to the time asked. Its gains follow the samples' spacing:

- growing memory first, the exact least-squares line through the k + 1 samples so far
  (alpha_k = 2(2k + 1) / ((k + 1)(k + 2)), beta_k = 6 / ((k + 1)(k + 2)), k >= 1);
- then fading memory of time constant tau = ``time_constant_s``, critically damped:
  theta = exp(-dt / tau), alpha = 1 - theta^2, beta = (1 - theta)^2 (Brown's double
  exponential smoothing; Morrison, "Introduction to Sequential Smoothing and Prediction",
  the fading-memory polynomial filter of degree 1),

whichever gain is larger; offset += alpha r, skew += beta r / dt for a residual r. Fixed
per-sample gains (0.05 and 0.025, before 4d4d589) were underdamped and made the skew's noise
grow with the request rate: at PX4's 50 Hz on a busy host it swung by +-7000 ppm (a 60 ppm
clock), and any pause in the answers (a port change, a stall) was extrapolated with it, 2-13
ms off. Several successive samples far from the estimate (an autopilot reboot: its clock jumps
back) reset the filter, as PX4 does.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

# PX4's requester side (src/lib/timesync/Timesync.{hpp,cpp}, PX4 1.14 to main 2026): the
# figures its filter is built on, modelled by :class:`RequesterModel`
PX4_CONVERGENCE_WINDOW = 500  # fused answers before PX4 converts our stamps
PX4_GAINS_INITIAL = (0.05, 0.05)  # (alpha, beta) at the first answer
PX4_GAINS_FINAL = (0.003, 0.003)  # (alpha, beta) from the convergence window on
PX4_MAX_RTT_SAMPLE_NS = 10_000_000  # MAX_RTT_SAMPLE: an answer whose round trip is not
# below it is discarded (neither fused nor an outlier: it cannot reset the filter)
PX4_MAX_DEVIATION_NS = 100_000_000  # MAX_DEVIATION_SAMPLE: this far off is an outlier
PX4_MAX_CONSECUTIVE_DEVIATIONS = 5  # MAX_CONSECUTIVE_HIGH_DEVIATION: one more in a row resets
# Our estimate of PX4's reception time of an answer may come out before the request's ts1:
# PX4 SIH's lockstep clock ticks in 4 ms steps (its requests leave on a step, its stamps of our
# requests read the step it is in) and a link is not symmetric. Measured on loopback against a
# real PX4 SIH (2026-11-29): estimates -4.3 .. +2.9 ms (1st .. 99th percentile) while PX4's own
# round trip was 0 for every answer. An answer cannot arrive before its request: an estimate
# down to this far below 0 is PX4's 0, not a reason to discard it.
RTT_ESTIMATE_SLACK_NS = 5_000_000


@dataclass(frozen=True, slots=True)
class TimesyncReply:
    """The fields of a TIMESYNC answer: tc1 = our clock [ns], ts1 = the request's ts1."""

    tc1: int
    ts1: int


def reply_for(tc1: int, ts1: int, now_ns: int) -> TimesyncReply | None:
    """The answer to a received TIMESYNC, or None when it is itself an answer (tc1 != 0)."""
    if tc1 != 0:
        return None
    return TimesyncReply(now_ns, ts1)


class ClockSync:
    """Offset (and skew) of a peer's clock against ours from TIMESYNC round trips (the
    companion uses it for the autopilot's clock, the SITL autopilot for the companion's)."""

    def __init__(
        self,
        max_rtt_ns: int = 10_000_000,
        time_constant_s: float = 3.0,
        max_deviation_ns: int = PX4_MAX_DEVIATION_NS,
        max_consecutive_deviations: int = PX4_MAX_CONSECUTIVE_DEVIATIONS,
    ) -> None:
        self.max_rtt_ns = max_rtt_ns
        self.time_constant_ns = time_constant_s * 1e9
        self.max_deviation_ns = max_deviation_ns
        self.max_consecutive_deviations = max_consecutive_deviations
        self.resets = 0  # times the estimate was dropped (autopilot clock jumps)
        self.recent_rtt_ns: deque[int] = deque(maxlen=32)
        self.slow_skipped = 0
        self.reset()

    def reset(self) -> None:
        """Forget the estimate (start again from the next sample)."""
        self.offset_ns = 0.0  # local - remote [ns] at time ref_ns (local clock)
        self.skew = 0.0  # d(offset)/d(time) [ns/ns]
        self.ref_ns = 0
        self.samples = 0
        self.last_rtt_ns = 0
        self.deviations = 0
        # the latest outlier's offset [ns] while outliers come in a row (a jump being
        # confirmed: where the fast answers put the peer's clock now), else None
        self.deviant_offset_ns: float | None = None

    @property
    def converged(self) -> bool:
        """True once enough good samples were seen to trust the estimate."""
        return self.samples >= 5

    @property
    def settled(self) -> bool:
        """Converged, and the latest answers agree with the estimate (False while a clock
        jump is being confirmed): a requester asks faster while it is not."""
        return self.converged and self.deviations == 0

    @property
    def fast_rtt_ns(self) -> int:
        """The recent round trips' 20th percentile [ns] (0 before any): the link's round trip
        when nothing waits in a buffer."""
        if not self.recent_rtt_ns:
            return 0
        ranked_rtt_ns = sorted(self.recent_rtt_ns)
        return ranked_rtt_ns[len(ranked_rtt_ns) // 5]

    def offset_at(self, now_ns: int) -> float:
        """The estimated offset local - remote [ns] at our time now_ns."""
        return self.offset_ns + self.skew * (now_ns - self.ref_ns)

    def on_reply(self, tc1: int, ts1: int, now_ns: int) -> bool:
        """Fuse the answer (tc1 = peer's ns, ts1 = our request time ns) received at
        now_ns; False when it was rejected (too slow, from the future, or an outlier)."""
        rtt = now_ns - ts1
        if rtt < 0 or rtt > self.max_rtt_ns:
            return False
        self.last_rtt_ns = rtt
        self.recent_rtt_ns.append(rtt)
        mid = (ts1 + now_ns) // 2
        measured = float(mid - tc1)
        if self.samples == 0:
            self.offset_ns, self.skew, self.ref_ns = measured, 0.0, mid
            self.samples = 1
            return True
        # a clock jump (the peer rebooted) first: an answer within max_rtt_ns cannot be
        # max_deviation_ns off through its delay, so a slow one counts as evidence too (on a
        # busy host most answers are slower than twice the fast ones: skipped first, they kept
        # the old offset for 8 s after a reboot, every stamp of the peer "from the past")
        predicted = self.offset_at(mid)
        if abs(measured - predicted) > self.max_deviation_ns:
            self.deviations += 1
            self.deviant_offset_ns = measured
            if self.deviations >= self.max_consecutive_deviations:
                self.resets += 1
                self.reset()
            return False
        self.deviations = 0
        self.deviant_offset_ns = None
        # "fast" is the recent round trips' 20th percentile, not their minimum: where round
        # trips spread evenly (PX4's lockstep answers in 4 ms steps: 0-4 ms) the minimum let
        # one answer in ten through, and at 2 Hz the estimate coasted for 10 s at a time
        if self.samples >= 5:
            fast_rtt_ns = self.fast_rtt_ns
            if rtt > max(2 * fast_rtt_ns, fast_rtt_ns + 500_000):
                self.slow_skipped += 1
                return False
        dt = mid - self.ref_ns
        if dt <= 0:  # an answer older than the last one fused (out of order): nothing new
            return False
        alpha, beta = self._gains(dt)
        error = measured - predicted
        self.offset_ns = predicted + alpha * error
        self.skew += beta * error / dt
        self.ref_ns = mid
        self.samples += 1
        return True

    def _gains(self, dt_ns: int) -> tuple[float, float]:
        """(alpha, beta) for the next sample, dt_ns after the previous one: the growing-memory
        least-squares gains until the fading-memory ones are larger (module docstring)."""
        k = self.samples  # samples fused so far: this one is sample k (from 0)
        alpha_ls = 2.0 * (2 * k + 1) / ((k + 1) * (k + 2))
        beta_ls = 6.0 / ((k + 1) * (k + 2))
        theta = math.exp(-dt_ns / self.time_constant_ns)
        alpha_fm, beta_fm = 1.0 - theta * theta, (1.0 - theta) ** 2
        return (alpha_ls, beta_ls) if alpha_ls > alpha_fm else (alpha_fm, beta_fm)

    def remote_to_local_us(self, remote_us: int, now_ns: int) -> int:
        """A timestamp of the peer's clock [us] in ours [us] (the offset as of now_ns)."""
        return int(round(remote_us + self.offset_at(now_ns) * 1e-3))


class RequesterModel:
    """What a TIMESYNC requester (PX4) makes of the answers we give it: whether it converts
    our ``time_usec`` stamps into its clock, or stamps our samples with their arrival.

    PX4's Timesync::update (src/lib/timesync/Timesync.cpp), answer by answer:

    1. round trip = its reception time - ts1 (unsigned: an answer "from the future" is huge);
       not below PX4_MAX_RTT_SAMPLE_NS: discarded, nothing else happens (no outlier count);
    2. once converged (PX4_CONVERGENCE_WINDOW fused answers since the last reset), an answer
       whose offset is over PX4_MAX_DEVIATION_NS from the estimate is an outlier; more than
       PX4_MAX_CONSECUTIVE_DEVIATIONS in a row reset the filter (a jump of either clock; in
       SITL, PX4's lockstep clock falling behind ours when the simulator stalls: 187 ms in one
       PX4 SIH flight);
    3. otherwise the answer is fused (double exponential smoothing, gains scheduled from
       PX4_GAINS_INITIAL to PX4_GAINS_FINAL over the window) and the outlier count cleared.

    PX4 converts our stamps only while converged; for ~500 answers after a reset (10 s at
    50 Hz) it stamps our samples on arrival, our latency late (~100 ms: 0.3 m at 3 m/s).
    Nothing on the link says so; this model follows PX4's filter on the same answers (each
    request's ts1, PX4's clock, against the tc1 we answered with).

    Step 1 needs PX4's reception time of our answer, which the model estimates with ``clock``,
    our own estimate of PX4's clock (:class:`ClockSync`, from our requests): our answer's time
    in PX4's clock, minus ts1, plus the link's fast round trip for the way back (the upper
    side: a whole round trip where half is due). Until ``clock`` has converged no answer can
    be shown to pass, so none is counted. That check is what keeps the model with PX4 when
    answers are late: a serial link that delivered requests 0-100 ms late (PX4 fused 8-9 % of
    the answers, the model without it counted them all), a stall of our loop (the requests
    queued meanwhile, answered at once 0.2 s late, counted as outliers: a false "clock
    jumped"), forged requests (their ts1 is no time PX4 just sent at: PX4 discards our answers
    to them by their round trip). Without ``clock`` the round trip is taken as 0 (a peer on
    loopback that answers at once: the test harness of the real PX4).

    The model still cannot see answers lost on the way to PX4, so it needs ``margin`` more
    answers than PX4 before it says ``converts``: erring toward "not converted" is the cheap
    side (the service then sends poses as of their sending, right in both states of PX4).
    Offsets in ns, PX4's clock minus ours (PX4's sign)."""

    def __init__(self, margin: float = 0.2, clock: ClockSync | None = None) -> None:
        self.needed = int(round(PX4_CONVERGENCE_WINDOW * (1.0 + margin)))
        self.clock = clock
        self.resets = 0  # resets seen after the first answer (clock jumps)
        self.answers = 0
        self.rtt_discarded = 0  # answers PX4 discards for their round trip (or unknown one)
        self.last_rtt_ns: int | None = None  # the latest answer's round trip, as estimated
        self.reset()

    def reset(self) -> None:
        """PX4's filter as at boot (also: the autopilot went silent, it may have rebooted)."""
        self.sequence = 0
        self.offset_ns = 0.0
        self.skew_ns = 0.0  # per answer, as PX4 keeps it
        self.deviations = 0

    @property
    def converts(self) -> bool:
        """True when the requester converts our stamps (its filter converged, with margin)."""
        return self.sequence >= self.needed

    def round_trip_ns(self, ts1_ns: int, tc1_ns: int) -> int | None:
        """PX4's round trip [ns] for our answer (tc1, our clock) to its request (ts1, its
        clock), estimated on the long side; None while ``clock`` has no estimate.

        While ``clock`` is confirming a jump (its fast answers disagree with it), the offset
        they point to is tried too: PX4's own answers come back fast across the jump, so it
        sees the outliers at once, and so must the model (it would otherwise wait for our
        estimate to reset and converge again, ~1 s, saying "converts" meanwhile)."""
        clock = self.clock
        if clock is None:
            return 0
        offsets_ns = [clock.offset_at(tc1_ns)] if clock.converged else []
        if clock.deviations and clock.deviant_offset_ns is not None:
            offsets_ns.append(clock.deviant_offset_ns)
        rtt_ns = None
        for offset_ns in offsets_ns:  # offset: ours - PX4's
            rtt_ns = int(round(tc1_ns - offset_ns - ts1_ns)) + clock.fast_rtt_ns
            if -RTT_ESTIMATE_SLACK_NS <= rtt_ns < 0:
                rtt_ns = 0  # before its request: our estimate's error (RTT_ESTIMATE_SLACK_NS)
            if 0 <= rtt_ns < PX4_MAX_RTT_SAMPLE_NS:
                break
        return rtt_ns

    def on_answer(self, ts1_ns: int, tc1_ns: int) -> None:
        """A request (its ts1, the requester's clock [ns]) we answered with tc1 [ns] (ours)."""
        self.answers += 1
        rtt_ns = self.round_trip_ns(ts1_ns, tc1_ns)
        self.last_rtt_ns = rtt_ns
        if rtt_ns is None or not 0 <= rtt_ns < PX4_MAX_RTT_SAMPLE_NS:
            self.rtt_discarded += 1
            return
        observed = float(ts1_ns + rtt_ns // 2 - tc1_ns)  # (ts1 + its reception) / 2 - tc1
        if self.sequence >= PX4_CONVERGENCE_WINDOW:
            if abs(self.offset_ns - observed) > PX4_MAX_DEVIATION_NS:
                self.deviations += 1
                if self.deviations > PX4_MAX_CONSECUTIVE_DEVIATIONS:
                    self.resets += 1
                    self.reset()
                return
            alpha, beta = PX4_GAINS_FINAL
        else:
            # PX4's gain schedule: a sigmoid from the initial to the final gains
            progress = self.sequence / PX4_CONVERGENCE_WINDOW
            p = 1.0 - math.exp(0.5 * (1.0 - 1.0 / (1.0 - progress)))
            alpha = p * PX4_GAINS_FINAL[0] + (1.0 - p) * PX4_GAINS_INITIAL[0]
            beta = p * PX4_GAINS_FINAL[1] + (1.0 - p) * PX4_GAINS_INITIAL[1]
        if self.sequence == 0:
            self.offset_ns = observed
        else:
            previous = self.offset_ns
            self.offset_ns = alpha * observed + (1.0 - alpha) * (self.offset_ns + self.skew_ns)
            self.skew_ns = beta * (self.offset_ns - previous) + (1.0 - beta) * self.skew_ns
        self.sequence += 1
        self.deviations = 0
