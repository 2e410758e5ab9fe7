"""The VO's frontend: the forward-backward KLT check, KLT on normalised images across an
exposure change, and the pixel options scaled to the image."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from companion.geometry.camera import CameraModel
from companion.vo.frontend import Tracks, detect, normalized_grey, scaled_to_image, track
from companion.vo.options import VoOptions


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0, 255, (60, 80)).astype(np.float32)
    img = cv2.resize(coarse, (640, 480), interpolation=cv2.INTER_CUBIC)
    out: np.ndarray = np.clip(img, 0, 255).astype(np.uint8)
    return out


def test_forward_backward_check_drops_tracks_that_lost_their_patch() -> None:
    """The image moves by (5, 3) px, and its right half is replaced (something new in view):
    KLT still reports most features there as found, at wrong places; back into the first
    image they do not come home, and the check drops them, while the left half's true
    tracks stay."""
    before = _texture(1)
    after = np.roll(before, (3, 5), axis=(0, 1))
    after[:, 320:] = _texture(2)[:, 320:]
    camera = CameraModel(640, 480, 400.0, 400.0, 320.0, 240.0)
    px = detect(before, np.zeros((0, 2), np.float32), 200, 18.0)
    tracks = Tracks.empty().extend(px, 0, np.zeros((len(px), 2)))
    wrong, kept_left = {}, {}
    for fb_px in (0.0, 1.0):
        opts = dataclasses.replace(VoOptions(), klt_fb_max_px=fb_px, min_distance_px=1.0)
        out = track(before, after, tracks, camera, opts)
        assert out.prev_px is not None
        err_px = np.linalg.norm(out.px - (out.prev_px + np.array([5.0, 3.0])), axis=1)
        wrong[fb_px] = int((err_px > 1.0).sum())
        kept_left[fb_px] = int(((out.prev_px[:, 0] < 300) & (err_px < 1.0)).sum())
    assert wrong[0.0] > 50  # without the check, half the tracks are wrong
    assert wrong[1.0] < 0.25 * wrong[0.0]
    assert kept_left[1.0] >= 0.95 * kept_left[0.0] > 50  # the true tracks stay


def test_min_distance_scales_down_with_a_smaller_image_only_when_automatic() -> None:
    auto = VoOptions()
    assert auto.min_distance_px == 0.0
    assert scaled_to_image(auto, 640, 480).min_distance_px == 18.0
    assert scaled_to_image(auto, 320, 240).min_distance_px == 9.0
    assert scaled_to_image(auto, 752, 480).min_distance_px == 18.0  # EuRoC: never enlarged
    assert scaled_to_image(auto, 1280, 360).min_distance_px == 0.75 * 18.0
    # a value set by hand is the camera's own tuning (config/px4_sitl.toml: 10 px at
    # 320 x 240), never scaled again
    tuned = dataclasses.replace(auto, min_distance_px=10.0)
    assert scaled_to_image(tuned, 320, 240) is tuned


def test_klt_on_normalised_images_follows_an_exposure_change() -> None:
    """The image moves by (5, 3) px while the exposure halves (an auto-exposure leaving a
    shadow): KLT on the raw grey levels loses nearly every feature, on normalised images
    (vo.klt_normalize) it keeps them all, in place."""
    before = _texture(1)
    moved = np.roll(before, (3, 5), axis=(0, 1)).astype(np.float64)
    after = np.clip(0.5 * moved + 10.0, 0, 255).astype(np.uint8)
    camera = CameraModel(640, 480, 400.0, 400.0, 320.0, 240.0)
    px = detect(before, np.zeros((0, 2), np.float32), 200, 18.0)
    tracks = Tracks.empty().extend(px, 0, np.zeros((len(px), 2)))
    right = {}
    for normalize in (False, True):
        opts = dataclasses.replace(VoOptions(), klt_normalize=normalize)
        out = track(before, after, tracks, camera, opts)
        assert out.prev_px is not None
        err_px = np.linalg.norm(out.px - (out.prev_px + np.array([5.0, 3.0])), axis=1)
        right[normalize] = int((err_px < 0.5).sum())
    assert right[False] < 0.1 * len(px)
    assert right[True] > 0.95 * len(px)
    # the normalisation itself: a gain and an offset are gone, to a grey level
    a = normalized_grey(before).astype(np.float64)
    b = normalized_grey(np.clip(0.5 * before + 10.0, 0, 255).astype(np.uint8))
    assert np.abs(a - b).max() <= 1.0 and abs(a.mean() - 128.0) < 1.0


def test_thin_keeps_what_the_greedy_pass_over_every_track_keeps() -> None:
    """thin runs its greedy pass over the crowded tracks only: on random crowded sets the
    kept tracks are those of the plain pass over all tracks (points first, then older)."""
    from companion.vo.frontend import thin

    rng = np.random.default_rng(7)
    for trial in range(30):
        n = int(rng.integers(2, 150))
        px = (rng.random((n, 2)) * [160, 120]).astype(np.float32)  # crowded: 18 px apart
        pid = np.where(rng.random(n) < 0.6, np.arange(n), -1).astype(np.int64)
        tracks = Tracks(px, pid, np.zeros(n, np.int64), np.zeros((n, 2)))
        r2 = (0.5 * 18.0) ** 2
        d2 = ((px[:, None, :].astype(np.float64) - px[None, :, :]) ** 2).sum(axis=2)
        close = d2 < r2
        np.fill_diagonal(close, False)
        keep, blocked = np.zeros(n, bool), np.zeros(n, bool)
        for i in np.lexsort((np.arange(n), pid < 0)):
            if not blocked[i]:
                keep[i] = True
                blocked |= close[i]
        out = thin(tracks, 18.0)
        assert np.array_equal(out.pid, pid[keep]), trial
        assert np.array_equal(out.px, px[keep])
