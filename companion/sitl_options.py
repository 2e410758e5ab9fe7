"""Options of the simulated ground and distance sensors (composed into the config as
[sitl.ground] and [sitl.rangefinder]; issue "A simulator as hard as reality").

Every effect is off by default: with these defaults every rendered frame and every range
reading is the one the simulator made before they existed (tests/sitl/world/test_surfaces.py
pins it). They sit beside `config.py`, below the simulator that reads them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from companion.options import opt

SurfaceName = Literal[
    "photo", "tiles", "checkerboard", "checker_sheets", "parking", "concrete", "carpet"
]
BelowMinReading = Literal["min", "zero", "saturated"]


@dataclass(frozen=True, slots=True)
class GroundOptions:
    """What covers the ground of any terrain, and what moves on it."""

    surface: SurfaceName = opt(
        "photo",
        "photo (grass and gravel photos), tiles (0.5 m floor tiles with grout), checkerboard "
        "(squares of checker_m), checker_sheets (those squares printed on overlapping sheets "
        "of paper), parking (asphalt with painted bays), concrete or carpet (low texture)",
    )
    checker_m: float = opt(
        0.3,
        "side of a checkerboard square [m] (checkerboard, checker_sheets; printed: 0.03-0.1)",
        gt=0.005,
        le=2.0,
    )
    specular_patches: float = opt(
        0.0, "share of the ground under water-like specular patches (0 = none)", ge=0, le=0.5
    )
    specular_strength: float = opt(
        0.8, "a patch's highlight at the mirror direction [share of full white]", ge=0, le=2
    )
    specular_exponent: float = opt(
        12.0, "Phong exponent of a patch's highlight (rippled water: 5-30)", ge=1, le=1000
    )
    downwash_m: float = opt(
        0.0,
        "grass displacement by the rotors' downwash under the vehicle [m] (0 = off)",
        ge=0,
        le=0.2,
    )
    downwash_radius_m: float = opt(
        2.0, "radius of the downwash's disturbed grass around the vehicle's ground point [m]", gt=0
    )
    shadow: bool = opt(False, "the vehicle's own soft shadow, cast along the sun direction")
    shadow_radius_m: float = opt(
        0.35, "radius of the vehicle's shadow (its full-dark core) [m]", gt=0, le=5
    )


@dataclass(frozen=True, slots=True)
class RangeEffects:
    """TFmini-class distance sensors as they are (on top of each sensor's noise, dropout and
    outlier fields of [[rangefinders]])."""

    bias_sigma_m: float = opt(
        0.0, "sigma of each sensor's constant bias, drawn once per seed and sensor [m]", ge=0, le=1
    )
    beam_fov_deg: float = opt(
        3.6,
        "full beam divergence, for depth edges inside it (TFmini Plus 3.6, TFmini-S 2)",
        gt=0,
        le=30,
    )
    edge_jump_m: float = opt(
        0.3, "spread of distances inside the beam that makes a depth edge [m]", gt=0
    )
    edge_outlier_prob: float = opt(
        0.0, "on a depth edge: probability of a mixed-pixel or wild reading", ge=0, le=1
    )
    edge_wild_share: float = opt(
        0.3, "share of the edge outliers that are wild (uniform in range), not mixed", ge=0, le=1
    )
    specular_miss_prob: float = opt(
        0.0, "on a specular (water, glass) patch: probability of no return (invalid)", ge=0, le=1
    )
    specular_through_prob: float = opt(
        0.0, "on a specular patch: probability of reading through it, to the bottom", ge=0, le=1
    )
    below_min: BelowMinReading = opt(
        "min",
        "a true distance below min_m reads: min (min_m flagged invalid, as PX4 publishes), zero "
        "(TFmini Plus: Dist 0 when the return saturates) or saturated (TFmini-S: Dist -2, "
        "655.34 m as uint16 cm); all flagged invalid",
    )


@dataclass(frozen=True, slots=True)
class DeliveryFaults:
    """How the simulated camera delivers its frames: a capture that loses frames in bursts (a
    busy USB bus or driver) and stamps that jitter. A lost frame is never delivered (the
    samples of its interval come with the next one; its sequence number is skipped); a
    delivered frame's image is of its capture time, its stamp off it by the jitter."""

    loss_bursts_per_min: float = opt(
        0.0, "lossy periods begun per minute of flight, at random (0 = none)", ge=0, le=60
    )
    loss_burst_s: float = opt(10.0, "a lossy period's mean length [s] (exponential)", gt=0, le=600)
    loss_from_s: float = opt(
        0.0, "a lossy period of its own from this time of the flight [s] (a recording's)", ge=0
    )
    loss_to_s: float = opt(0.0, "... to this time [s] (<= loss_from_s: none)", ge=0)
    loss_in_burst: float = opt(
        0.4, "the probability that a frame is lost within a lossy period", ge=0, le=0.95
    )
    loss_run_frames: float = opt(
        1.0,
        "the mean number of frames lost in a row within a lossy period (runs of geometric "
        "length, the share lost still loss_in_burst; 1 = each frame lost on its own)",
        ge=1,
        le=100,
    )
    numbers_lost: bool = opt(
        True,
        "a lost frame's sequence number is skipped (the receiver sees the gap); false: the "
        "delivered frames are numbered 0, 1, 2, ... (a capture that numbers only what it "
        "delivers, as the real downward flight's image files are)",
    )
    stamp_jitter_ms: float = opt(
        0.0,
        "each delivered stamp off the capture time by up to +- this, uniformly [ms] (kept "
        "after the stamp before it)",
        ge=0,
        le=200,
    )
