"""A steady clock for camera frames whose time stamps jitter.

A camera exposes its frames at a steady rate, but the stamps it delivers can jitter by a large
part of a frame: a driver that stamps on arrival, frames delivered in pairs (measured on a real
downward camera: intervals of 2 ms and 64 ms alternating while the image moved evenly). The VO
predicts each frame's motion over its interval (constant velocity, scaled by the ratio of this
interval to the last one), so a 2/64 ms alternation predicts 32 times the real motion every
other frame, and the tracking breaks.

``FrameClock`` models the stamps as a line over the frame count, ``t_k = a + b k`` (least
squares over the last ``window`` frames; ``k`` counts frames by their sequence numbers, so
frames dropped upstream keep their place), and judges the clock by the root mean square of
the residuals:

- at most ``max(min_jitter_ms, jitter_fraction * b)`` (a steady clock, e.g. the simulator's
  or a good driver's): every stamp is passed through unchanged; so it is when every interval
  is a whole number (at least one) of the median interval within that tolerance: a steady
  clock whose lost frames the sequence numbers do not count (a source that numbers only the
  frames it kept, as a converted TUM RGB-D list does);
- above it: the frame is re-timed to the line, ``a + b k`` (rounded to a microsecond, kept
  strictly after the previous frame), and counted in ``retimed``. A re-timed frame follows
  the one before it by ``b`` per frame step, pulled by ``pull`` (0.1) of the way towards the
  line: the line's end moves with each new stamp by a few percent of a frame (a least-squares
  end point has the most leverage), and the interval the VO scales its prediction by
  should not.

A stamp more than ``max(break_intervals * b, break_min_ms)`` off the line is a break of the
clock (the camera paused or restarted): the line starts again from that frame, which keeps
its own stamp. The line passes through the middle of the stamps, so re-timed frames carry
the mean latency of the jittery stamps rather than each frame's own error.

Units: times in integer microseconds (``time_us``), the report in milliseconds.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

MAX_SEQ_STEP = 100  # a larger step of the sequence number is not trusted (a restart)


@dataclass(frozen=True, slots=True)
class ClockReport:
    """What the clock found over its window: the steady period [ms], the stamps' rms
    distance to the line [ms], the shortest and longest stamp intervals [ms] per frame step,
    the frames in the window, whether the clock is judged jittery now, and the frames
    re-timed so far."""

    period_ms: float
    jitter_rms_ms: float
    min_interval_ms: float
    max_interval_ms: float
    frames: int
    jittery: bool
    retimed: int


class FrameClock:
    """Re-times frames whose stamps jitter (``time_us(seq, time_us)`` -> the frame's time)."""

    def __init__(
        self,
        window: int = 60,
        min_frames: int = 10,
        jitter_fraction: float = 0.1,
        min_jitter_ms: float = 2.0,
        break_intervals: float = 4.0,
        break_min_ms: float = 200.0,
        pull: float = 0.1,
    ) -> None:
        self.window = window
        self.min_frames = min_frames
        self.jitter_fraction = jitter_fraction
        self.min_jitter_us = min_jitter_ms * 1e3
        self.break_intervals = break_intervals
        self.break_min_us = break_min_ms * 1e3
        self._k: deque[int] = deque(maxlen=window)  # frame count of each stamp in the window
        self._t: deque[int] = deque(maxlen=window)  # its stamp [us]
        self._last_seq: int | None = None
        self._last_out_us: int | None = None
        self._fit: tuple[float, float, float] | None = None  # (a, b, rms) of the last fit
        self._last_steady: float | None = None  # the last re-timed frame's time [us]
        self.pull = pull
        self.retimed = 0
        self.breaks = 0

    def time_us(self, seq: int, time_us: int) -> int:
        """The time of the frame with sequence number ``seq`` stamped ``time_us``: the stamp
        itself on a steady clock, else the steady line's time at this frame."""
        step = 1
        if self._last_seq is not None and 1 <= seq - self._last_seq <= MAX_SEQ_STEP:
            step = seq - self._last_seq
        self._last_seq = seq
        k = self._k[-1] + step if self._k else 0
        if self._fit is not None:
            a, b, _ = self._fit
            off_us = abs(time_us - (a + b * (k - self._k[0])))
            if off_us > max(self.break_intervals * b, self.break_min_us):
                self._k.clear()
                self._t.clear()
                self._fit = None
                self._last_steady = None
                self.breaks += 1
                k = 0
        self._k.append(k)
        self._t.append(time_us)
        out_us = time_us
        if len(self._k) >= self.min_frames:
            a, b, rms = self._line()
            self._fit = (a, b, rms)
            if self._jittery(b, rms):
                line_us = a + b * (k - self._k[0])
                if self._last_steady is not None:  # one period on, pulled gently to the line
                    ahead_us = self._last_steady + b * step
                    line_us = ahead_us + self.pull * (line_us - ahead_us)
                self._last_steady = line_us
                out_us = int(round(line_us))
                self.retimed += 1
            else:
                self._last_steady = None
        if self._last_out_us is not None and out_us <= self._last_out_us:
            out_us = self._last_out_us + 1
        self._last_out_us = out_us
        return out_us

    def _jittery(self, b_us: float, rms_us: float) -> bool:
        """Whether the stamps in the window jitter: off their line by more than the tolerance,
        and not the stamps of a steady clock that lost frames the sequence numbers do not
        count (a source that numbers only the frames it kept). Those intervals are whole
        numbers ``n >= 1`` of a base period ``P``: ``P`` starts as their 10th percentile (at
        least half the line's slope: with fewer than half the frames lost), ``n`` is each
        interval over it, rounded, ``P`` is then fitted by least squares, and the intervals'
        rms residual from ``n P`` must be within the tolerance."""
        tol_us = max(self.min_jitter_us, self.jitter_fraction * b_us)
        if b_us <= 0 or rms_us <= tol_us:
            return False
        per_step = np.diff(np.asarray(self._t, np.float64)) / np.maximum(
            np.diff(np.asarray(self._k, np.float64)), 1.0
        )
        base_us = float(np.percentile(per_step, 10))
        if base_us < 0.5 * b_us:
            return True
        n = np.rint(per_step / base_us)
        if np.any(n < 1):
            return True
        period_us = float(per_step @ n) / float(n @ n)
        resid_us = per_step - n * period_us
        return float(np.sqrt(np.mean(resid_us**2))) > tol_us

    def _line(self) -> tuple[float, float, float]:
        """Least-squares line ``t = a + b (k - k0)`` over the window and the rms residual."""
        k = np.asarray(self._k, dtype=np.float64) - self._k[0]
        t = np.asarray(self._t, dtype=np.float64)
        k_mean, t_mean = float(k.mean()), float(t.mean())
        dk = k - k_mean
        var = float(dk @ dk)
        b = float(dk @ (t - t_mean)) / var if var > 0 else 0.0
        a = t_mean - b * k_mean
        rms = float(np.sqrt(np.mean((t - (a + b * k)) ** 2)))
        return a, b, rms

    def report(self) -> ClockReport | None:
        """The clock over its current window, None before ``min_frames`` frames."""
        if self._fit is None or len(self._k) < 2:
            return None
        _, b, rms = self._fit
        k = np.asarray(self._k, dtype=np.float64)
        t = np.asarray(self._t, dtype=np.float64)
        per_step = np.diff(t) / np.maximum(np.diff(k), 1.0)
        jittery = self._jittery(b, rms)
        return ClockReport(
            period_ms=b * 1e-3,
            jitter_rms_ms=rms * 1e-3,
            min_interval_ms=float(per_step.min()) * 1e-3,
            max_interval_ms=float(per_step.max()) * 1e-3,
            frames=len(self._k),
            jittery=bool(jittery),
            retimed=self.retimed,
        )


def jitter_warning(report: ClockReport) -> str:
    """One line for an operator: how the stamps jitter and what is done about it."""
    return (
        f"camera time stamps jitter: intervals {report.min_interval_ms:.1f}..."
        f"{report.max_interval_ms:.1f} ms per frame around a steady {report.period_ms:.1f} ms "
        f"(rms {report.jitter_rms_ms:.1f} ms off a steady clock over {report.frames} frames); "
        f"{report.retimed} frames re-timed to the steady clock (vo.steady_clock)"
    )
