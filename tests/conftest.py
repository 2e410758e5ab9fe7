"""Shared fixtures: seeded worlds are expensive to build, so build each once per session."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from functools import cache

import pytest

# matplotlib's FreeType module is loaded before anything in this process can load GStreamer:
# once GStreamer was initialised (its plugins bring the system's libfreetype), the first
# `import matplotlib.ft2font` (any plot) aborted the whole pytest process (SIGABRT, reproduced:
# tests/test_camera.py's GStreamer tests, then the ArduPilot loop's plot). Loading it first
# avoids that, whatever order the tests run in.
with contextlib.suppress(ImportError):  # no eval extra: nothing plots, nothing to protect
    import matplotlib.ft2font  # noqa: F401

from companion.config import Config, load_config
from sitl.world import World, make_world


@cache
def _world(name: str, seed: int) -> World:
    return make_world(name, seed)


@pytest.fixture(scope="session")
def world() -> Callable[[str, int], World]:
    """world(name, seed) -> a cached World."""
    return _world


@pytest.fixture(scope="session")
def default_config() -> Config:
    """The built-in (SITL) configuration."""
    return load_config()
