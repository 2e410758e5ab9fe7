"""A whole simulated flight: world + trajectory + camera + distance sensors + attitude.

``Scenario(cfg).steps()`` yields, frame by frame, the rendered camera frame and every range and
attitude sample since the previous frame, with ground truth. The same stream feeds the dataset
recorder, offline evaluation and (later) the SITL autopilot, so all see identical data.
"""

from __future__ import annotations

import os
import threading
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from companion.config import Config
from companion.sitl.world.render import RenderedFrame, Renderer
from companion.sitl.world.sensors import AttitudeSimulator, RangeSimulator, TrueRange
from companion.sitl.world.terrain import World, make_world
from companion.sitl.world.trajectory import Trajectory
from companion.types import F64, AttitudeSample, CameraFrame


def render_threads() -> int:
    """Threads worth rendering on: one per core this process may use, at most 4."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(4, cores or 1))


@dataclass(frozen=True, slots=True)
class Step:
    """One camera frame and the samples since the previous one (times <= frame time)."""

    frame: CameraFrame
    rendered: RenderedFrame
    T_world_body: F64
    ranges: list[TrueRange]
    attitudes: list[AttitudeSample]


class Scenario:
    """The flight described by ``cfg.sitl`` with the sensors of ``cfg``."""

    def __init__(self, cfg: Config, world: World | None = None) -> None:
        s = cfg.sitl
        self.cfg = cfg
        self.world = world or make_world(
            s.terrain, s.seed, s.world_size_m, s.height_resolution_m, s.ground
        )
        self.trajectory = Trajectory(
            s.trajectory, self.world, s.seconds, s.altitude_m, s.speed_m_s, s.takeoff_landing
        )
        self.renderer = Renderer(self.world, cfg.camera, s.render, cfg.rangefinders, s.seed)
        self.ranges = RangeSimulator(
            self.world, self.trajectory, cfg.rangefinders, s.seed, s.rangefinder
        )
        self.attitude = AttitudeSimulator(self.trajectory, s.seed)
        self.frame_period_s = 1.0 / cfg.camera.rate_hz
        self.n_frames = int(np.floor(s.seconds * cfg.camera.rate_hz + 1e-9))

    def frame_time_us(self, seq: int) -> int:
        """Capture (mid-exposure) time of frame ``seq`` [us]."""
        return int(round(seq * self.frame_period_s * 1e6))

    def step(self, seq: int) -> Step:
        """Frame ``seq`` and the samples in (time of frame seq-1, time of frame seq]."""
        t_us = self.frame_time_us(seq)
        t_prev_s = self.frame_time_us(seq - 1) * 1e-6 if seq > 0 else -1.0
        t_s = t_us * 1e-6
        # sample windows are half-open [a, b); shift by 1 us to make them (prev, now]
        ranges = self.ranges.between(t_prev_s + 1e-6, t_s + 1e-6)
        atts = self.attitude.between(t_prev_s + 1e-6, t_s + 1e-6)
        rendered = self.renderer.render_at(self.trajectory, t_s, seq)
        T_world_body = self.trajectory.T_world_body(t_s)
        frame = CameraFrame(t_us, seq, rendered.image_bgr)
        return Step(frame, rendered, T_world_body, ranges, atts)

    def steps(self, start: int = 0, stop: int | None = None, workers: int = 1) -> Iterator[Step]:
        """Frames start..stop-1 in order. ``workers`` > 1: rendered ahead (at most 2 x workers
        steps) on that many threads, each with a Scenario of its own over this world; the render
        kernels run without the GIL and step k depends on k alone (every noise is seeded by
        its frame or sample time), so the steps are those of one thread
        (tests/sitl/world/test_render.py)."""
        stop = self.n_frames if stop is None else min(stop, self.n_frames)
        if workers <= 1:
            for seq in range(start, stop):
                yield self.step(seq)
            return
        _ = self.world.textures  # built once, before the threads share the world
        local = threading.local()

        def step(seq: int) -> Step:
            mine: Scenario | None = getattr(local, "scenario", None)
            if mine is None:
                mine = local.scenario = Scenario(self.cfg, world=self.world)
            return mine.step(seq)

        with ThreadPoolExecutor(workers, thread_name_prefix="scenario") as pool:
            ahead: deque[Future[Step]] = deque()
            seq = start
            while seq < stop or ahead:
                while seq < stop and len(ahead) < 2 * workers:
                    ahead.append(pool.submit(step, seq))
                    seq += 1
                yield ahead.popleft().result()
