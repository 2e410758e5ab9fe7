"""The PX4 parameters that decide whether EKF2 fuses our estimate: what we need and why.

One row per parameter: its value, what we need, why (in PX4's terms), a status, and the
value(s) ``configure`` would write. FAIL: EKF2 will not fuse our estimate (or the link will not
work) as it is. WARN: it works, but not as well as it should, or not as docs/service.md
recommends. OK: as needed. INFO: context only.

The rules follow PX4 1.14+ (EKF2_EV_CTRL / EKF2_HGT_REF, which replaced EKF2_AID_MASK /
EKF2_HGT_MODE) and docs/service.md: VISION_POSITION_ESTIMATE is NED and needs a
north-aligned heading; ODOMETRY (LOCAL_FRD / BODY_FRD, VISION) works at any heading; we stamp at
exposure and PX4 converts through TIMESYNC, so EKF2_EV_DELAY stays 0 where the link time-syncs;
our covariance is real, so EKF2 should use it (EKF2_EV_NOISE_MD 0) with the noise parameters as
floors. Defaults differ between versions (EKF2_EV_CTRL: 15 before PX4 1.16, 0 since); PX4
after 1.16 configures ports with SER_<port>_PROT and MAV_ETH_EN instead of MAV_n_CONFIG, and
the link rows follow whichever the firmware has; where it has none of them (PX4 SITL, whose
start-up script starts the MAVLink instances) there is nothing to set, and no version string is
trusted for it (a build from an untagged commit reports v0.0.0).

EKF2_EV_CTRL bit 3 (yaw), as the real PX4 (SITL, main 2026-03) showed it: VISION_POSITION_ESTIMATE
needs it without a magnetometer (else EKF2's heading never aligns and NED is never fused) and may
have it with one; ODOMETRY (LOCAL_FRD) must not have it (EKF2 then never aligns its heading and
PX4 refuses to arm) and needs a magnetometer for the same reason.
"""

from __future__ import annotations

from collections.abc import Mapping

from companion.autopilot.params import Param, Row
from companion.autopilot.px4.ekf2_rules import ekf2_rows
from companion.autopilot.px4.gps_rules import with_gps
from companion.autopilot.px4.link_context import LinkContext
from companion.autopilot.px4.port_rules import link_rows


def evaluate(params: Mapping[str, Param], ctx: LinkContext) -> list[Row]:
    """Every row, EKF2 first (with ``ctx.with_gps``: judged for GPS and vision together,
    :mod:`.gps_rules`), then the companion's MAVLink instance."""
    ekf2 = ekf2_rows(params, ctx)
    if ctx.with_gps:
        ekf2 = with_gps(ekf2, params, ctx)
    return [*ekf2, *link_rows(params, ctx)]
