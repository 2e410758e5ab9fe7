"""The VO's keyframe policy: a keyframe while hovering only when the tracks run low."""

from __future__ import annotations

import numpy as np

from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.vo.frontend import Tracks
from companion.vo.keyframes import need_keyframe
from companion.vo.map import VoMap
from companion.vo.options import VoOptions


def _tracks(n: int, rng: np.random.Generator) -> Tracks:
    px = rng.uniform([0, 0], [640, 480], (n, 2)).astype(np.float32)
    return Tracks(px, np.arange(n, dtype=np.int64), np.zeros(n, np.int64), np.zeros((n, 2)))


def test_a_hover_takes_a_keyframe_only_when_the_tracks_run_low() -> None:
    """Turning in place (fr1/rpy) or hovering, the camera does not move: a keyframe would add
    no parallax, so none is taken for coverage or age; but when fewer than 30 % of
    ``max_features`` are still tracked (the view turned away), one is, for its new
    features: else the tracks starve before the camera moves again."""
    rng = np.random.default_rng(4)
    opts = VoOptions()
    camera = CameraModel(640, 480, 400.0, 400.0, 320.0, 240.0)
    last = VoMap().new_keyframe(0, np.eye(4))
    last.obs = {p: np.zeros(2) for p in range(200)}
    still = se3.make(np.eye(3), [0.001, 0.0, 0.0])  # 0.1 % of the 1 m depth
    args = (1.0, 100, camera, opts)  # depth, frames since the keyframe (old), ...
    assert not need_keyframe(last, still, _tracks(100, rng), *args)  # half left: no
    assert need_keyframe(last, still, _tracks(50, rng), *args)  # a quarter left: yes
    off = (1.0, 100, camera, VoOptions(kf_low_tracks_ratio=0.0))
    assert not need_keyframe(last, still, _tracks(50, rng), *off)  # off: only when moving
    moved = se3.make(np.eye(3), [0.2, 0.0, 0.0])  # 20 % of the depth: always
    assert need_keyframe(last, moved, _tracks(190, rng), *args)
