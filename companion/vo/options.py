"""Options of the visual odometry (one frozen dataclass, composed into the config as [vo])."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from companion.options import opt

HeadingSource = Literal["autopilot", "magnetometer"]


@dataclass(frozen=True, slots=True)
class VoOptions:
    """Tuning of the monocular VO; defaults are for 640x480 at 30 Hz looking down."""

    max_features: int = opt(200, "features kept in tracking", ge=20, le=2000)
    min_distance_px: float = opt(
        0.0,
        "minimum distance between features [px]; 0 = 18 px at 640 x 480, scaled down with a "
        "smaller image (320 x 240: 9 px), never up (companion/vo/frontend.py scaled_to_image)",
        ge=0,
    )
    klt_window_px: int = opt(15, "KLT window side [px]", ge=5, le=61)
    klt_levels: int = opt(3, "KLT pyramid levels above the image", ge=0, le=6)
    klt_predict_min_px: float = opt(
        8.0, "predicted flow above which the KLT starts from the prediction [px]", ge=0
    )
    klt_normalize: bool = opt(
        False,
        "KLT on images normalised to one mean and contrast (an auto-exposure's changes "
        "removed; companion/vo/frontend.py normalized_grey)",
    )
    learn_lens: bool = opt(
        False,
        "take the focal length and k1 that the in-flight lens check finds (once, when it warns; "
        "the VO restarts with them) instead of only warning (companion/pipeline/lens_stage.py)",
    )
    klt_fb_max_px: float = opt(
        0.0,
        "drop a track that KLT back into the previous frame returns farther than this from "
        "its start (forward-backward check: a repeated texture) [px]; 0 = off (1 for a "
        "camera over a repeated pattern: config/real_camera.toml)",
        ge=0,
    )
    pixel_sigma_px: float = opt(1.0, "feature position noise [px]", gt=0)
    inlier_px: float = opt(2.5, "pose inlier threshold on reprojection error [px]", gt=0)
    min_tracked_points: int = opt(25, "fewer 3D points tracked than this = LOST", ge=6)
    init_min_parallax_px: float = opt(22.0, "median flow before two-view init [px]", gt=0)
    init_min_points: int = opt(60, "tracked features needed to initialise", ge=8)
    init_max_frames: int = opt(90, "frames before the init reference is renewed", ge=5)
    kf_translation_ratio: float = opt(
        0.10, "new keyframe after this translation / median depth", gt=0, le=1
    )
    kf_tracked_ratio: float = opt(0.65, "new keyframe when fewer of the KF's points track", gt=0)
    kf_min_coverage: float = opt(
        0.5, "new keyframe when tracked points cover less of a 4 x 4 image grid", ge=0, le=1
    )
    kf_low_tracks_ratio: float = opt(
        0.3,
        "new keyframe (for its new features) when fewer tracks than this share of "
        "max_features are left, even while hovering or turning in place; 0 = only when moving",
        ge=0,
        le=1,
    )
    kf_max_frames: int = opt(20, "at most this many frames between keyframes (when moving)", ge=1)
    min_parallax_deg: float = opt(1.0, "minimum triangulation angle [deg]", gt=0)
    gravity_sigma_deg: float = opt(
        1.0,
        "the autopilot's roll/pitch as a prior on the local BA's keyframes (sigma) [deg]; "
        "0 = images only",
        ge=0,
    )
    axial_gravity_sigma_deg: float = opt(
        0.0,
        "the prior's sigma on keyframes reached by moving along the optical axis (a take-off's "
        "climb, a landing: the images cannot tell a tilt from a sideways move there) [deg]; "
        "0 = gravity_sigma_deg (off). 0.5 halves a take-off's climb error with a good attitude "
        "but cost one VO reset in a low 12 m/s urban flight (docs/decisions.md)",
        ge=0,
    )
    axial_max_angle_deg: float = opt(
        30.0,
        "a keyframe is axial when the camera moved within this angle of its optical axis "
        "since the previous keyframe [deg]",
        gt=0,
        le=90,
    )
    pad_gravity_sigma_deg: float = opt(
        0.0,
        "gravity for the BA's prior from the distance sensors while over the take-off pad (its "
        "plane measured at rest with the autopilot's attitude, companion/attitude/pad.py), at "
        "least this sigma [deg]; 0 = off. Assumes the pad is one plane under the sensors' hits "
        "up to the climb's top (a floor, a landing mat): docs/decisions.md",
        ge=0,
    )
    pad_radius_m: float = opt(
        1.5, "the pad's gravity only within this horizontal distance of the rest [m]", gt=0
    )
    pad_window_s: float = opt(
        0.5, "the pad's gravity: the autopilot's tilt error averaged over this long [s]", gt=0
    )
    imu_gravity_window_s: float = opt(
        4.0,
        "gravity for the BA's prior also from the autopilot's accelerometer against our own "
        "motion over this window (when SCALED_IMU arrives) [s]; 0 = the attitude's alone",
        ge=0,
        le=30,
    )
    heading_source: HeadingSource = opt(
        "autopilot",
        "the VO frame's heading: the autopilot's when the VO initialises, or (magnetometer) "
        "then our own tilt-compensated compass averaged while the vehicle stands still "
        "(SCALED_IMU's raw field, companion/attitude/heading.py): docs/decisions.md",
    )
    mag_declination_deg: float = opt(
        0.0,
        "the site's magnetic declination for heading_source = magnetometer [deg, east "
        "positive]: look it up for the site (a WMM calculator)",
        ge=-180,
        le=180,
    )
    mag_heading_min_s: float = opt(
        5.0,
        "heading_source = magnetometer: the field averaged this long at rest before the frame "
        "takes its heading (then refined until the vehicle moves) [s]",
        gt=0,
    )
    window_keyframes: int = opt(6, "keyframes optimised by the local bundle adjustment", ge=2)
    max_keyframes: int = opt(10, "keyframes kept in the map (older ones dropped)", ge=2)
    ba_iterations: int = opt(4, "Levenberg-Marquardt iterations of the local BA", ge=0, le=50)
    ba_iterations_per_frame: int = opt(
        0,
        "0: the local BA runs all its iterations in its keyframe's work; N: it starts there "
        "and takes N iterations in each frame's work after it, its result applied when it "
        "ends (the keyframe's work shorter; companion/vo/odometry.py refine_map)",
        ge=0,
        le=50,
    )
    max_rotation_deg_per_frame: float = opt(
        25.0, "a larger rotation between frames is a failure (LOST)", gt=0
    )
    rotation_hold_frames: int = opt(
        30,
        "when the pose against the map fails but the 2D tracks fit one rotation of the camera "
        "(turning in place: no parallax, so the map starves), follow that rotation with the "
        "position held for at most this many frames in a row before LOST (companion/vo/"
        "rotation.py); 0 = off",
        ge=0,
    )
    rotation_min_inlier_ratio: float = opt(
        0.7,
        "the rotation hold needs this share of the tracks within rotation_inlier_px of it",
        gt=0,
        le=1,
    )
    rotation_inlier_px: float = opt(
        6.0, "a track farther than this off the held rotation is an outlier [px]", gt=0
    )
    rotation_depth_prior: float = opt(
        0.5,
        "a keyframe taken while the rotation is held gives its untriangulated features a point "
        "at the scene's median depth with this relative depth sigma (refined by the local BA "
        "once the camera moves); 0 = off (they stay candidates)",
        ge=0,
    )
    max_gap_ms: float = opt(
        1000.0,
        "a longer gap between usable frames loses tracking (new VO map) [ms]; a shorter one "
        "is tracked across with the motion predicted over it",
        gt=0,
    )
    steady_clock: bool = opt(
        True,
        "re-time frames whose stamps jitter by more than 10 % of a frame (2 ms at least) to "
        "the steady line of their stamps over the frame count (companion/vo/frame_clock.py)",
    )
    ground_init: bool = opt(
        True, "initialise metrically on the ground plane the distance sensors see (no parallax)"
    )
    ground_max_height_m: float = opt(
        1.5, "ground initialisation only with the camera this close to the plane [m]", gt=0
    )
    ground_window_ms: float = opt(
        500.0, "range readings averaged for the ground plane (the vehicle at rest) [ms]", gt=0
    )
    ground_max_rms_m: float = opt(
        0.03, "the readings must fit one plane this well (rms height residual) [m]", gt=0
    )
    landed_camera_height_m: float = opt(
        0.0,
        "camera height above the ground on the landing gear [m], used when >= 3 sensors read "
        "below their minimum (too close); 0 = unknown",
        ge=0,
    )
    dark_level: float = opt(12.0, "a frame whose mean grey level is below this is dark", ge=0)
    bright_level: float = opt(243.0, "a frame whose mean grey level is above this is saturated")
    min_contrast: float = opt(3.0, "a frame whose grey-level std is below this is blank", ge=0)
