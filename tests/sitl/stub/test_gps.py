"""The SITL autopilot's GPS receiver (sitl/stub/gps.py): its fixes land, through the service's
projection (companion/frames/gnss.py), where the truth is; its noise has the sigma and the
correlation time it claims; a lost fix carries no position."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.frames.gnss import GlobalOrigin, GnssOptions, GpsFix, sample_reasons, to_local_ned
from companion.sitl.stub import gps


@pytest.mark.parametrize("ned", [(0.0, 0.0, 0.0), (120.0, -80.0, -30.0), (-900.0, 1500.0, 2.0)])
def test_a_fix_maps_back_to_its_point_within_the_messages_resolution(ned: tuple) -> None:
    mav = mavlink.MAVLink(None)
    msg = gps.gps_raw_int(mav, 0, np.array(ned), False, np.zeros(3))
    o = gps.gps_global_origin(mav, 0)
    origin = GlobalOrigin.from_message(o.latitude, o.longitude, o.altitude)
    fix = GpsFix.from_gps_raw_int(0, msg.fix_type, msg.lat, msg.lon, msg.alt, msg.eph, 12)
    back = to_local_ned(origin, fix.lat_deg, fix.lon_deg, fix.alt_m, "px4")
    assert np.abs(back - np.array(ned)).max() < 0.012  # 1e-7 deg ~ 1.1 cm, 1 mm in height
    assert sample_reasons(fix, GnssOptions()) == ()


def test_a_lost_fix_is_bad_and_has_no_position() -> None:
    msg = gps.gps_raw_int(mavlink.MAVLink(None), 0, np.ones(3), True, np.zeros(3))
    fix = GpsFix.from_gps_raw_int(0, msg.fix_type, msg.lat, msg.lon, msg.alt, msg.eph, 3)
    assert msg.lat == 0 and msg.lon == 0
    assert len(sample_reasons(fix, GnssOptions())) == 3  # fix type, eph, satellites


def test_the_noise_has_its_sigma_and_correlation_time() -> None:
    noise = gps.GpsNoise(0.3, 1.0, seed=5)
    t = np.arange(0.0, 2000.0, 0.2)
    x = np.array([noise.at(float(s)) for s in t])
    assert np.std(x, axis=0) == pytest.approx([0.3] * 3, rel=0.1)
    lag = 5  # 1 s: the correlation exp(-1)
    r = np.mean([np.corrcoef(x[:-lag, i], x[lag:, i])[0, 1] for i in range(3)])
    assert r == pytest.approx(math.exp(-1.0), abs=0.05)
    again = gps.GpsNoise(0.3, 1.0, seed=5)
    assert np.array_equal(again.at(0.0), x[0])  # seeded


def test_a_gps_loss_is_a_fault_in_the_others_syntax() -> None:
    from companion.sitl.stub.faults import Fault, active

    f = Fault.parse("gps_loss@12+10")
    assert (f.kind, f.start_s, f.end_s) == ("gps_loss", 12.0, 22.0)
    assert active([f], 11.9) == set() and active([f], 12.0) == {"gps_loss"}
    assert active([f], 22.0) == set()
