"""Shared fixtures: seeded worlds are expensive to build, so build each once per session."""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

import pytest

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
