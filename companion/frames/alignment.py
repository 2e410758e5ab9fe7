"""Our published track against the autopilot's GPS-derived one: a 4-DoF alignment (pure).

Frames: both tracks are local NED [m] (x north, y east, z down), gravity-aligned on both
sides, so roll and pitch agree and the frames differ by a yaw about z and a translation:

    p_ref = Rz(yaw_rad) p_ours + translation_ned_m          (a :class:`FrameAlignment`)

with Rz the rotation about NED z (positive from north towards east, as a NED heading).

The fit (:func:`fit_track`) over a window of N time-matched pairs (ours a_i, theirs b_i, both
(N, 3), optional weights w_i):

* yaw from the track: the closed form of Horn (1987) / Umeyama (1991) restricted to a rotation
  about z, without scale, on the weighted-centred horizontal points a'_i, b'_i:
  ``yaw = atan2(sum w (a'x b'y - a'y b'x), sum w (a'x b'x + a'y b'y))``. It is observable only
  when our track spans some distance: its sigma is ~ position noise / travel [rad].
* yaw from the attitudes (:func:`attitude_yaw`): the weighted circular mean of
  (their yaw - our yaw) over the pairs, always available, as good as the two headings.
* the two fused by inverse variance (track sigma = ``position_sigma_m / travel_m``); a window
  with less than ``min_travel_m`` of travel (a hover) takes the attitude yaw alone.
* then ``t_xy = mean_w(b_xy) - R mean_w(a_xy)`` and ``t_z = mean_w(b_z - a_z)``.

The residual RMS of ``b - (R a + t)`` is "how well we agree" with the autopilot; the mean residual
over the whole window is zero by construction, so the trend is the mean over the newest quarter.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from companion.geometry import so3
from companion.types import F64, PoseEstimate

TRAVEL_PER_RMS_RADIUS = math.sqrt(12.0)  # a straight leg of length L: RMS radius L / sqrt(12)


def wrap_rad(angle_rad: float) -> float:
    """An angle in [-pi, pi)."""
    return float((angle_rad + math.pi) % (2.0 * math.pi) - math.pi)


@dataclass(frozen=True, slots=True, eq=False)
class FrameAlignment:
    """p_ref = Rz(yaw_rad) p_ours + translation_ned_m; translation_ned_m: (3,) [m]."""

    yaw_rad: float
    translation_ned_m: F64

    @staticmethod
    def identity() -> FrameAlignment:
        """Our own frame: no yaw, no translation."""
        return FrameAlignment(0.0, np.zeros(3))

    def rotation(self) -> F64:
        """Rz(yaw_rad), (3, 3)."""
        return so3.rot_z(self.yaw_rad)

    def apply_points(self, points_ned_m: ArrayLike) -> F64:
        """Our positions (3,) or (N, 3) [m] in the reference frame."""
        p = np.asarray(points_ned_m, dtype=np.float64)
        out: F64 = p @ self.rotation().T + self.translation_ned_m
        return out

    def inverse(self) -> FrameAlignment:
        """The alignment that maps the reference frame back to ours."""
        R_inv = so3.rot_z(-self.yaw_rad)
        return FrameAlignment(wrap_rad(-self.yaw_rad), -(R_inv @ self.translation_ned_m))


def apply(T: FrameAlignment, pose: PoseEstimate) -> PoseEstimate:
    """``pose`` (our NED position, R_world_body quaternion, velocity, covariance) in the
    reference frame: position Rz p + t, attitude Rz R, velocity Rz v, and the covariance's
    position rows and columns turned by Rz (roll, pitch, yaw variances are unchanged by a turn
    about z; NaN entries stay NaN and do not spread)."""
    R = T.rotation()
    q = so3.matrix_to_quat(R @ so3.quat_to_matrix(pose.quat_wxyz_ned_frd))
    return dataclasses.replace(
        pose,
        position_ned_m=R @ pose.position_ned_m + T.translation_ned_m,
        quat_wxyz_ned_frd=q,
        velocity_ned_m_s=R @ pose.velocity_ned_m_s,
        covariance_6x6=_turn_covariance(R, pose.covariance_6x6),
    )


def pose_yaw(pose: PoseEstimate) -> float:
    """The heading [rad] of a pose's attitude (ZYX yaw of R_world_body)."""
    return float(so3.matrix_to_rpy(so3.quat_to_matrix(pose.quat_wxyz_ned_frd))[2])


def _turn_covariance(R: F64, cov: F64) -> F64:
    """M cov M^T with M = blockdiag(R, I3); entries whose inputs hold a NaN are NaN."""
    M = np.eye(6)
    M[:3, :3] = R
    known = np.isfinite(cov)
    out: F64 = M @ np.where(known, cov, 0.0) @ M.T
    # an output entry depends on the inputs that M mixes into it: NaN if any of those is NaN
    mixes = (np.abs(M) > 0).astype(np.float64)
    unknown = (mixes @ (~known).astype(np.float64) @ mixes.T) > 0
    out[unknown] = np.nan
    return out


@dataclass(frozen=True, slots=True)
class PairWindow:
    """Time-matched pairs: time_us (N,) on the reference's stamps; ours_ned_m, ref_ned_m (N, 3)
    [m]; our_yaw_rad, ref_yaw_rad (N,) [rad] (NaN: no heading at that pair); reset_counter (N,)
    our reset counter at the pair (our frame changes with it)."""

    time_us: np.ndarray
    ours_ned_m: F64
    ref_ned_m: F64
    our_yaw_rad: F64
    ref_yaw_rad: F64
    reset_counter: np.ndarray

    def __len__(self) -> int:
        return int(self.time_us.shape[0])

    def take(self, keep: np.ndarray) -> PairWindow:
        """The pairs selected by ``keep`` (a boolean mask or indices)."""
        return PairWindow(
            self.time_us[keep],
            self.ours_ned_m[keep],
            self.ref_ned_m[keep],
            self.our_yaw_rad[keep],
            self.ref_yaw_rad[keep],
            self.reset_counter[keep],
        )

    def latest_epoch(self) -> PairWindow:
        """The pairs in the frame of our newest reset counter (older ones are another frame)."""
        if len(self) == 0:
            return self
        return self.take(self.reset_counter == self.reset_counter[-1])


def match_pairs(
    ours_time_us: ArrayLike,
    ours_ned_m: ArrayLike,
    ours_yaw_rad: ArrayLike,
    ours_reset_counter: ArrayLike,
    ref_time_us: ArrayLike,
    ref_ned_m: ArrayLike,
    ref_yaw_rad: ArrayLike | None = None,
    max_gap_us: int = 200_000,
) -> PairWindow:
    """Our track (M samples, increasing ``ours_time_us``) interpolated at the reference's
    stamps (N): linear in position, along the shorter arc in yaw. A reference stamp outside
    our track, between two of our samples more than ``max_gap_us`` apart, or between two of
    ours with different reset counters (a reset: two frames) makes no pair."""
    t = np.asarray(ours_time_us, dtype=np.int64)
    p = np.asarray(ours_ned_m, dtype=np.float64).reshape(-1, 3)
    yaw = np.asarray(ours_yaw_rad, dtype=np.float64)
    reset = np.asarray(ours_reset_counter, dtype=np.int64)
    rt = np.asarray(ref_time_us, dtype=np.int64)
    rp = np.asarray(ref_ned_m, dtype=np.float64).reshape(-1, 3)
    ryaw = np.full(rt.shape, np.nan) if ref_yaw_rad is None else np.asarray(ref_yaw_rad, np.float64)
    i1 = np.searchsorted(t, rt, side="right")  # first of ours after the stamp
    i0 = i1 - 1  # last of ours at or before it
    exact = (i0 >= 0) & (t[np.clip(i0, 0, None)] == rt)
    inside = (i0 >= 0) & (i1 < len(t))
    a, b = np.clip(i0, 0, len(t) - 1), np.clip(i1, 0, len(t) - 1)
    ok = exact | (inside & (t[b] - t[a] <= max_gap_us) & (reset[a] == reset[b]))
    span = np.maximum(t[b] - t[a], 1).astype(np.float64)
    alpha = np.where(exact, 0.0, (rt - t[a]) / span)[:, None]
    pos = p[a] + alpha * (p[b] - p[a])
    dyaw = (yaw[b] - yaw[a] + math.pi) % (2.0 * math.pi) - math.pi
    our_yaw = (yaw[a] + alpha[:, 0] * dyaw + math.pi) % (2.0 * math.pi) - math.pi
    return PairWindow(rt, pos, rp, our_yaw, ryaw, reset[a]).take(ok)


@dataclass(frozen=True, slots=True)
class FitOptions:
    """position_sigma_m: the reference's position noise (GPS: correlated, ~0.3 m) for the
    track yaw's sigma; attitude_sigma_rad: the floor under the attitude yaw's sigma (two
    headings, each a degree or so); min_travel_m: below this travel the track yaw is not used."""

    position_sigma_m: float = 0.3
    attitude_sigma_rad: float = math.radians(2.0)
    min_travel_m: float = 2.0


@dataclass(frozen=True, slots=True)
class TrackFit:
    """The alignment fitted over a window and how well the two tracks agree under it.

    residual_rms_m: RMS of |b - (R a + t)| [m] (the agreement); residual_rms_ned_m: (3,) the
    same per axis; recent_mean_residual_ned_m: (3,) the mean residual over the newest quarter
    of the pairs (the whole window's is zero by construction: this shows a trend); travel_m:
    the horizontal extent of our track (sqrt(12) x its RMS radius: a straight leg of length L
    gives L); yaw_source: "track", "attitude" or "both"; yaw_sigma_rad: the fused yaw's sigma;
    newest_us: the newest pair's stamp."""

    alignment: FrameAlignment
    residual_rms_m: float
    residual_rms_ned_m: F64
    recent_mean_residual_ned_m: F64
    travel_m: float
    pairs: int
    yaw_track_rad: float
    yaw_attitude_rad: float
    yaw_sigma_rad: float
    yaw_source: str
    newest_us: int


def track_yaw(ours_ned_m: F64, ref_ned_m: F64, weights: F64) -> tuple[float, float]:
    """(yaw_rad, travel_m) of the closed-form horizontal fit on weighted-centred points."""
    w = weights / weights.sum()
    a = ours_ned_m[:, :2] - w @ ours_ned_m[:, :2]
    b = ref_ned_m[:, :2] - w @ ref_ned_m[:, :2]
    s = float(w @ (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    c = float(w @ (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    travel = TRAVEL_PER_RMS_RADIUS * math.sqrt(float(w @ (a * a).sum(axis=1)))
    return math.atan2(s, c), travel


def attitude_yaw(our_yaw_rad: F64, ref_yaw_rad: F64, weights: F64) -> tuple[float, float] | None:
    """(yaw_rad, spread_rad): the weighted circular mean of wrap(ref - ours) over the pairs
    with both headings, and the circular standard deviation sqrt(-2 ln R); None without any."""
    d = ref_yaw_rad - our_yaw_rad
    ok = np.isfinite(d)
    if not ok.any():
        return None
    w = weights[ok] / weights[ok].sum()
    c, s = float(w @ np.cos(d[ok])), float(w @ np.sin(d[ok]))
    r = min(1.0, math.hypot(c, s))
    spread = math.sqrt(-2.0 * math.log(r)) if r > 1e-12 else math.pi
    return math.atan2(s, c), spread


def fit_track(
    pairs: PairWindow, weights: ArrayLike | None = None, opts: FitOptions | None = None
) -> TrackFit | None:
    """The 4-DoF alignment of ``pairs`` (module docstring); None with fewer than 2 pairs, or
    when the yaw is unobservable (less than ``min_travel_m`` of travel and no headings)."""
    o = opts or FitOptions()
    n = len(pairs)
    if n < 2:
        return None
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (n,) or not np.all(w >= 0) or w.sum() <= 0:
        raise ValueError(f"weights: {n} non-negative values with a positive sum expected")
    a, b = pairs.ours_ned_m, pairs.ref_ned_m
    yaw_tr, travel = track_yaw(a, b, w)
    att = attitude_yaw(pairs.our_yaw_rad, pairs.ref_yaw_rad, w)
    sigma_tr = o.position_sigma_m / max(travel, 1e-9)
    if att is None and travel < o.min_travel_m:
        return None
    if att is None:
        yaw, sigma, source = yaw_tr, sigma_tr, "track"
    else:
        sigma_att = max(o.attitude_sigma_rad, att[1])
        if travel < o.min_travel_m:
            yaw, sigma, source = att[0], sigma_att, "attitude"
        else:
            k = sigma_att**2 / (sigma_att**2 + sigma_tr**2)
            yaw = att[0] + k * wrap_rad(yaw_tr - att[0])
            sigma = math.sqrt(1.0 / (1.0 / sigma_att**2 + 1.0 / sigma_tr**2))
            source = "both"
    wn = w / w.sum()
    R = so3.rot_z(yaw)
    t = wn @ b - R @ (wn @ a)
    t[2] = float(wn @ (b[:, 2] - a[:, 2]))
    alignment = FrameAlignment(wrap_rad(yaw), t)
    r = b - alignment.apply_points(a)
    recent = r[-max(1, n // 4) :]
    return TrackFit(
        alignment=alignment,
        residual_rms_m=math.sqrt(float(wn @ (r * r).sum(axis=1))),
        residual_rms_ned_m=np.sqrt(wn @ (r * r)),
        recent_mean_residual_ned_m=recent.mean(axis=0),
        travel_m=travel,
        pairs=n,
        yaw_track_rad=yaw_tr if travel >= o.min_travel_m else math.nan,
        yaw_attitude_rad=att[0] if att is not None else math.nan,
        yaw_sigma_rad=sigma,
        yaw_source=source,
        newest_us=int(pairs.time_us[-1]),
    )
