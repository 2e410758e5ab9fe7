"""EKF2's lag behind our output, carried into the output at a GPS loss ([gps] px4_loss_carry;
docs/gps.md, "EKF2's lag carried at the loss"; the maths: :mod:`companion.frames.carry`).

Inputs: the autopilot's LOCAL_POSITION_NED (``on_local_position``: its time_boot_ms on our clock
[us], NED [m]) and every output we send (``on_output``), each kept for ~2 s. At the loss
(``at_loss``, the GPS frame's held transition with PX4 told): the mean (EKF2 - ours) over the
last CARRY_WINDOW_US, which the GPS frame adds to the handover's applied alignment
(``Handover.carry``: the slew takes it out again); EKF2_GPS_CTRL 0 is then to wait
CARRY_SWITCH_DELAY_S, so that EKF2's reset onto our position lands on a carried pose. Nothing
follows EKF2 afterwards: the difference is measured while EKF2 fuses GNSS and frozen at the
loss.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from companion.frames.carry import autopilot_offset
from companion.types import F64

log = logging.getLogger("companion.service")

CARRY_WINDOW_US = 500_000  # EKF2's lag behind our output: averaged over this long before a loss
# EKF2_GPS_CTRL 0 this long after the lag is carried: EKF2 resets onto the EV sample at its
# delayed horizon, which must already be a carried pose (3-frame centred ODOMETRY: ~70 ms)
CARRY_SWITCH_DELAY_S = 0.3
KEPT_SAMPLES = 128  # the autopilot's positions and our outputs kept (~2 s of each)


class LagCarry:
    """The autopilot's positions and our outputs, and the lag carried at the latest loss."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.ap_positions: deque[tuple[int, F64]] = deque(maxlen=KEPT_SAMPLES)
        self.outputs: deque[tuple[int, F64]] = deque(maxlen=KEPT_SAMPLES)
        self.dropped = 0  # LOCAL_POSITION_NED not finite or not 3 values
        self.carried_m: float | None = None  # the lag carried at the latest loss [m]

    def on_local_position(self, time_us: int, position_ned_m: F64) -> None:
        """The autopilot's own position (kept only when enabled); a non-finite one dropped."""
        if not self.enabled:
            return
        p = np.asarray(position_ned_m, np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            self.dropped += 1
            return
        self.ap_positions.append((time_us, p))

    def on_output(self, time_us: int, position_ned_m: F64) -> None:
        """A pose we send, in the frame the autopilot receives it (kept only when enabled)."""
        if self.enabled:
            self.outputs.append((time_us, np.asarray(position_ned_m, np.float64)))

    def at_loss(self, time_us: int) -> F64 | None:
        """At a loss with PX4 told: EKF2's lag behind our output (3,) NED [m], z 0, to carry
        into it, EKF2_GPS_CTRL 0 then waiting CARRY_SWITCH_DELAY_S; None: nothing to carry
        (off, or no LOCAL_POSITION_NED in the window before ``time_us``)."""
        self.carried_m = None
        if not self.enabled:
            return None
        ap, outs = list(self.ap_positions), list(self.outputs)
        offset = autopilot_offset(
            np.array([a[0] for a in ap], dtype=np.int64),
            np.array([a[1] for a in ap]).reshape(-1, 3),
            np.array([o[0] for o in outs], dtype=np.int64),
            np.array([o[1] for o in outs]).reshape(-1, 3),
            time_us,
            CARRY_WINDOW_US,
        )
        if offset is None:
            log.info("GPS frame: no LOCAL_POSITION_NED before the loss: no lag carried")
            return None
        self.carried_m = float(np.linalg.norm(offset))
        log.info(
            "GPS frame: EKF2's lag %.3f m N %.3f m E carried into our output",
            offset[0],
            offset[1],
        )
        return offset
