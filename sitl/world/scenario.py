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
from companion.sitl_options import DeliveryFaults
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
        self.lost = lost_frames(s.delivery, self.n_frames, self.frame_period_s, s.seed)
        self._lost_sorted = np.array(sorted(self.lost), dtype=np.int64)

    def frame_time_us(self, seq: int) -> int:
        """Capture (mid-exposure) time of frame ``seq`` [us]."""
        return int(round(seq * self.frame_period_s * 1e6))

    def stamp_us(self, seq: int) -> int:
        """The stamp frame ``seq`` is delivered with [us]: its capture time off by up to
        +- ``[sitl.delivery] stamp_jitter_ms``, uniformly (seeded by the frame), and at least
        1 ms after the stamp of every frame before (a running maximum over the frames whose
        jitter could reach it)."""
        jitter_us = self.cfg.sitl.delivery.stamp_jitter_ms * 1e3
        if jitter_us <= 0:
            return self.frame_time_us(seq)
        reach = int(np.ceil(2.0 * jitter_us / (self.frame_period_s * 1e6))) + 1
        return max(
            self._jittered_us(q) + 1000 * (seq - q) for q in range(max(0, seq - reach), seq + 1)
        )

    def _jittered_us(self, seq: int) -> int:
        """Frame ``seq``'s capture time plus its own jitter [us]."""
        u = np.random.default_rng([self.cfg.sitl.seed, 812, seq]).uniform(-1.0, 1.0)
        return int(
            round(self.frame_time_us(seq) + u * self.cfg.sitl.delivery.stamp_jitter_ms * 1e3)
        )

    def step(self, seq: int, since: int | None = None) -> Step:
        """Frame ``seq`` and the samples in (time of frame ``since``, time of frame seq]
        (``since``: the frame delivered before it; None: seq - 1)."""
        t_us = self.frame_time_us(seq)
        before = seq - 1 if since is None else since
        t_prev_s = self.frame_time_us(before) * 1e-6 if before >= 0 else -1.0
        t_s = t_us * 1e-6
        # sample windows are half-open [a, b); shift by 1 us to make them (prev, now]
        ranges = self.ranges.between(t_prev_s + 1e-6, t_s + 1e-6)
        atts = self.attitude.between(t_prev_s + 1e-6, t_s + 1e-6)
        rendered = self.renderer.render_at(self.trajectory, t_s, seq)
        T_world_body = self.trajectory.T_world_body(t_s)
        frame = CameraFrame(self.stamp_us(seq), self.delivered_seq(seq), rendered.image_bgr)
        return Step(frame, rendered, T_world_body, ranges, atts)

    def delivered_seq(self, seq: int) -> int:
        """The sequence number frame ``seq`` is delivered with: its own, or with
        ``[sitl.delivery] numbers_lost`` false its place among the delivered frames (the lost
        frames before it not counted)."""
        if self.cfg.sitl.delivery.numbers_lost or not len(self._lost_sorted):
            return seq
        return seq - int(np.searchsorted(self._lost_sorted, seq))

    def steps(self, start: int = 0, stop: int | None = None, workers: int = 1) -> Iterator[Step]:
        """Frames start..stop-1 in order. ``workers`` > 1: rendered ahead (at most 2 x workers
        steps) on that many threads, each with a Scenario of its own over this world; the render
        kernels run without the GIL and step k depends on k alone (every noise is seeded by
        its frame or sample time), so the steps are those of one thread
        (tests/sitl/world/test_render.py)."""
        stop = self.n_frames if stop is None else min(stop, self.n_frames)
        delivered = [q for q in range(start, stop) if q not in self.lost]
        since = {q: p for p, q in zip([start - 1, *delivered], delivered, strict=False)}
        if workers <= 1:
            for seq in delivered:
                yield self.step(seq, since[seq])
            return
        _ = self.world.textures  # built once, before the threads share the world
        local = threading.local()

        def step(seq: int) -> Step:
            mine: Scenario | None = getattr(local, "scenario", None)
            if mine is None:
                mine = local.scenario = Scenario(self.cfg, world=self.world)
            return mine.step(seq, since[seq])

        with ThreadPoolExecutor(workers, thread_name_prefix="scenario") as pool:
            ahead: deque[Future[Step]] = deque()
            todo = iter(delivered)
            pending = len(delivered)
            while pending or ahead:
                while pending and len(ahead) < 2 * workers:
                    ahead.append(pool.submit(step, next(todo)))
                    pending -= 1
                yield ahead.popleft().result()


def lost_frames(
    faults: DeliveryFaults, n_frames: int, frame_period_s: float, seed: int
) -> frozenset[int]:
    """The frames (sequence numbers in 0..n_frames-1) a capture with ``faults`` loses: lossy
    periods begun at random (a Poisson process of ``loss_bursts_per_min``), each of an
    exponential length of mean ``loss_burst_s``, and the one from ``loss_from_s`` to
    ``loss_to_s``, in which each frame is lost with probability ``loss_in_burst``; seeded,
    and the same whatever the frames asked for. With ``loss_run_frames`` > 1 the losses come
    in runs: a two-state chain (Gilbert's channel model) that stays in the lost state with
    probability 1 - 1/run, so runs are geometric with that mean, and enters it with the
    probability that keeps the share lost at ``loss_in_burst`` (a capture that stalls: the
    real downward flight's lossy stretch lost 43 % of its frames in runs of 7 on the mean,
    6.5 median, 14 at most; docs/decisions.md, "The look-alike's camera delivers as the real
    one did")."""
    fixed = faults.loss_to_s > faults.loss_from_s
    if (faults.loss_bursts_per_min <= 0 and not fixed) or faults.loss_in_burst <= 0:
        return frozenset()
    rng = np.random.default_rng([seed, 811])
    flight_s = n_frames * frame_period_s
    n_bursts = int(rng.poisson(faults.loss_bursts_per_min * flight_s / 60.0))
    starts_s = rng.uniform(0.0, flight_s, n_bursts)
    lengths_s = rng.exponential(faults.loss_burst_s, n_bursts)
    t_s = np.arange(n_frames) * frame_period_s
    in_burst = (t_s >= faults.loss_from_s) & (t_s < faults.loss_to_s)
    for a, length in zip(starts_s, lengths_s, strict=True):
        in_burst |= (t_s >= a) & (t_s < a + length)
    u = rng.random(n_frames)
    if faults.loss_run_frames <= 1.0:
        lose = in_burst & (u < faults.loss_in_burst)
    else:
        lose = _runs_lost(in_burst, u, faults.loss_in_burst, faults.loss_run_frames)
    if n_frames:
        lose[0] = False  # the first frame starts the stream
    return frozenset(np.flatnonzero(lose).tolist())


def _runs_lost(in_burst: np.ndarray, u: np.ndarray, share: float, run: float) -> np.ndarray:
    """(N,) bool: the frames a two-state chain loses within ``in_burst`` (N,) given uniform
    draws ``u`` (N,): lost after lost with probability 1 - 1/run, lost after delivered with
    share / (1 - share) / run (the chain's stationary share lost is then ``share``); every
    lossy stretch starts delivered."""
    stay = 1.0 - 1.0 / run
    enter = min(1.0, share / (1.0 - share) / run)
    lose = np.zeros(len(u), dtype=bool)
    prev = False
    for i in range(len(u)):
        prev = bool(in_burst[i]) and u[i] < (stay if prev else enter)
        lose[i] = prev
    return lose
