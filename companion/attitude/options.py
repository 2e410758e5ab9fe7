"""Options of the range-based roll/pitch estimation (composed into the config as [attitude])."""

from __future__ import annotations

from dataclasses import dataclass

from companion.options import opt


@dataclass(frozen=True, slots=True)
class AttitudeOptions:
    """Which sensors, the terrain compensation and the fusion with the VO rotation."""

    enabled: bool = opt(True, "estimate roll/pitch from the distance sensors")
    sensor_ids: tuple[int, ...] = opt((), "sensors used for roll/pitch (empty = all configured)")
    compensate: bool = opt(True, "remove the terrain's own tilt measured from the VO cloud")
    patch_radius_m: float = opt(
        0.6, "Gaussian radius of the cloud patch fitted around each hit point [m]", gt=0, le=10
    )
    min_patch_points: int = opt(6, "cloud points needed around a hit point", ge=3)
    max_patch_rms_m: float = opt(
        0.08, "a patch rougher than this (RMS about its fit) is refused [m]", gt=0
    )
    edge_gate_m: float = opt(
        0.15, "a hit this far from the cloud's surface is on an edge or another surface [m]", gt=0
    )
    min_spread_m: float = opt(0.02, "hit points closer than this to a line are collinear [m]", gt=0)
    max_tilt_deg: float = opt(
        60.0, "a ground plane tilted more than this from the body is refused [deg]", gt=0, le=85
    )
    max_terrain_tilt_deg: float = opt(
        40.0, "terrain under the hits steeper than this is refused [deg]", gt=0, le=85
    )
    drift_deg_per_sqrt_s: float = opt(
        0.05, "random walk of the VO frame's tilt error [deg / sqrt(s)]", ge=0
    )
    init_sigma_deg: float = opt(
        0.5, "sigma of the VO frame's tilt error at initialisation [deg]", gt=0
    )
    error_correlation_s: float = opt(
        2.0,
        "time over which tilt measurement errors stay correlated (the same cloud patch) [s]",
        ge=0,
    )
    fuse_ranges: bool = opt(
        False,
        "also fuse the range tilts (they share the VO frame's drift: docs/methods.md)",
    )
    autopilot_sigma_deg: float = opt(
        0.5,
        "sigma of the autopilot's roll/pitch as the fusion's gravity anchor [deg] (0 = unused)",
        ge=0,
    )
    autopilot_correlation_s: float = opt(
        1.0, "time over which the autopilot's roll/pitch errors stay correlated [s]", ge=0
    )
    gate_chi2: float = opt(13.8, "chi-square gate (2 dof) on a tilt measurement's innovation", gt=0)
