"""A ``[camera]`` table for the camera source tests (tests/drivers/test_camera*.py)."""

from __future__ import annotations

from companion.config import CameraConfig, load_config


def camera(
    width: int = 640, height: int = 480, rate_hz: float = 30.0, **more: object
) -> CameraConfig:
    """A [camera] table of this size (intrinsics scaled from the default)."""
    cfg = load_config(
        None,
        {"camera": {"width": width, "height": height, "rate_hz": rate_hz, **more}},
    )
    return cfg.camera
