"""GPS fixes: the local NED of each autopilot and the quality verdict (companion.frames.gnss)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.frames.gnss import (
    GlobalOrigin,
    GnssMonitor,
    GnssOptions,
    GpsFix,
    Projection,
    sample_reasons,
    to_local_ned,
)

# PX4 SIH's home (research: SIH_LOC_LAT0 / LON0 / H0)
HOME = GlobalOrigin(47.3977, 8.5456, 489.4)


@pytest.mark.parametrize(
    ("projection", "north_m"),
    [("px4", math.radians(0.001) * 6_371_000.0), ("ardupilot", 111.31884502145034)],
)
def test_a_thousandth_of_a_degree_of_latitude_is_111_m(
    projection: Projection, north_m: float
) -> None:
    """~111.3 m: 111.19 m on PX4's sphere, 111.32 m by ArduPilot's scaling factor (each
    autopilot's own, so a fix lands where its local position would)."""
    p = to_local_ned(HOME, HOME.lat_deg + 0.001, HOME.lon_deg, HOME.alt_m + 2.0, projection)
    assert p[0] == pytest.approx(north_m, abs=1e-3)
    assert p[0] == pytest.approx(111.3, abs=0.15)
    assert abs(p[1]) < 1e-6 and p[2] == pytest.approx(-2.0)
    east = to_local_ned(HOME, HOME.lat_deg, HOME.lon_deg + 0.001, HOME.alt_m, projection)
    assert east[1] == pytest.approx(north_m * math.cos(math.radians(HOME.lat_deg)), rel=1e-6)
    assert abs(east[0]) < 0.01  # PX4's azimuthal projection bends a parallel by mm at 75 m
    west = to_local_ned(HOME, HOME.lat_deg, HOME.lon_deg - 0.001, HOME.alt_m, projection)
    assert west[1] == pytest.approx(-east[1], rel=1e-9)


def test_the_two_projections_differ_by_0_11_percent_near_home() -> None:
    for d_lat, d_lon in ((0.0005, -0.0003), (-0.002, 0.004), (0.0, 0.0)):
        a = to_local_ned(HOME, HOME.lat_deg + d_lat, HOME.lon_deg + d_lon, 500.0, "px4")
        b = to_local_ned(HOME, HOME.lat_deg + d_lat, HOME.lon_deg + d_lon, 500.0, "ardupilot")
        assert np.linalg.norm(a - b) <= 1.2e-3 * np.linalg.norm(a[:2]) + 1e-9
        assert a[2] == b[2] == pytest.approx(-10.6)
    assert np.allclose(to_local_ned(HOME, HOME.lat_deg, HOME.lon_deg, HOME.alt_m, "px4"), 0.0)


def test_mavlink_fields_are_scaled_and_unknowns_kept_unknown() -> None:
    fix = GpsFix.from_gps_raw_int(5, 3, 473977000, 85456000, 489400, 90, 10)
    assert (fix.lat_deg, fix.lon_deg) == pytest.approx((47.3977, 8.5456))
    assert (fix.alt_m, fix.eph_m, fix.satellites) == pytest.approx((489.4, 0.9, 10))
    unknown = GpsFix.from_gps_raw_int(5, 3, 0, 0, 0, 65535, 255)
    assert unknown.eph_m == math.inf and unknown.satellites == -1
    assert len(sample_reasons(unknown, GnssOptions())) == 2  # eph and satellites unknown
    origin = GlobalOrigin.from_message(473977459, 85455930, 489400)
    assert (origin.lat_deg, origin.lon_deg, origin.alt_m) == pytest.approx(
        (47.3977459, 8.5455930, 489.4), abs=1e-9
    )


def _fix(t_s: float, fix_type: int = 3, eph_m: float = 0.9, satellites: int = 10) -> GpsFix:
    return GpsFix(int(t_s * 1e6), fix_type, 0.0, 0.0, 0.0, eph_m, satellites)


def test_the_verdict_drops_at_the_first_bad_fix_and_returns_after_3_s_of_good_ones() -> None:
    m = GnssMonitor()
    assert not m.at(0).good and m.at(0).reasons == ("no GPS sample yet",)
    verdicts = [m.update(_fix(0.2 * k)) for k in range(20)]  # 4 s at 5 Hz
    good = [v.good for v in verdicts]
    assert good.index(True) == 15  # 3.0 s after the first good fix
    lost = m.update(_fix(4.0, fix_type=0, eph_m=99.0, satellites=3))
    assert not lost.good and lost.bad_since_us == 4_000_000
    assert "fix type 0 < 3" in lost.reasons and "eph 99 m > 3 m" in lost.reasons
    assert "3 satellites < 6" in lost.reasons
    # the first good fix after the loss does not bring it back; 3 s of them do
    back = [m.update(_fix(4.2 + 0.2 * k)) for k in range(16)]
    assert back[0].sample_good and back[0].bad_since_us is None and not back[0].good
    assert [v.good for v in back].index(True) == 15
    noisy = m.update(_fix(7.6, eph_m=4.0))
    assert not noisy.good and noisy.bad_since_us == 7_600_000


def test_silence_is_a_loss_dated_at_its_start() -> None:
    m = GnssMonitor(GnssOptions(good_after_s=0.0))
    assert m.update(_fix(0.0)).good
    assert m.at(900_000).good
    silent = m.at(2_500_000)
    assert not silent.good and silent.bad_since_us == 1_000_000
    assert silent.reasons == ("no GPS sample for 2.5 s",)
    assert m.update(_fix(2.6)).good  # no return hysteresis with good_after_s = 0
    # a silence seen only by the next fix is a loss all the same: 3 s of good fixes to return
    unasked = GnssMonitor()
    assert [unasked.update(_fix(0.5 * k)).good for k in range(8)][-1]
    after = unasked.update(_fix(6.0))
    assert not after.good and after.sample_good and after.bad_since_us is None
    back = [unasked.update(_fix(6.0 + 0.2 * k)).good for k in range(1, 16)]
    assert back.index(True) == 14  # at 9.0 s


def test_a_slow_loss_verdict_waits_and_keeps_the_first_bad_stamp() -> None:
    m = GnssMonitor(GnssOptions(bad_after_s=1.0, good_after_s=0.0))
    m.update(_fix(0.0))
    v = [m.update(_fix(0.2 * k, eph_m=5.0)) for k in range(1, 8)]
    assert [x.good for x in v] == [True] * 5 + [False] * 2  # bad from 0.2 s, verdict at 1.2 s
    assert all(x.bad_since_us == 200_000 for x in v)
