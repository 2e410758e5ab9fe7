"""The rolling-shutter correction of the tracks where it cannot be undistorted
(VisualOdometry._drop_outside_lens)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.config import load_config
from companion.errors import GeometryError
from companion.vo.frontend import Tracks
from companion.vo.odometry import VisualOdometry

REPO = Path(__file__).resolve().parents[3]
LOOK_ALIKE = "config/like_real/downward_checkerboard.toml"


def test_a_track_carried_past_the_lens_by_the_shutter_is_dropped_not_raised() -> None:
    """Under a 20 ms rolling shutter the tracks are moved along their image motion to the
    frame's stamp. Over an interval of 1 us (a clock that keeps its stamps in order by a
    microsecond) a 4 px motion is 4e6 px/s, and a track 2 rows off the middle is carried to
    (-353, 888) px, where the look-alike's lens (k1 -0.33) does not invert: ``companion eval``
    of the look-alike with its frames numbered on stopped there (2026-12-02). Such tracks are
    dropped and counted; the others keep the coordinates ``frame_xy`` gives."""
    cfg = load_config(REPO / LOOK_ALIKE)
    vo = VisualOdometry(cfg.camera.model(), cfg.camera.T_body_cam(), cfg.vo, 0.02)
    assert vo.shutter is not None
    px = np.array([[204.50739, 122.22565], [160.0, 120.0], [200.0, 120.0]], np.float32)
    prev_px = np.array([[202.05212, 125.59546], [160.0, 120.0], [200.0, 120.0]], np.float32)
    vo.tracks = Tracks(px, np.array([3, 4, 5]), np.zeros(3, np.int64), vo.normalized(px), prev_px)
    vo.shutter.update(px, prev_px, 1e-6)
    with pytest.raises(GeometryError):
        vo.frame_xy(vo.tracks)
    vo.tracks.xy = None
    vo._drop_outside_lens()
    assert vo.outside_lens == 1 and list(vo.tracks.pid) == [4, 5]
    kept = vo.tracks.xy
    vo.tracks.xy = None
    assert kept is not None and np.array_equal(vo.frame_xy(vo.tracks), kept)
