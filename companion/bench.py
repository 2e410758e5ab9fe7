"""Benchmarks (figures for docs/BENCHMARKS.md): measured, never asserted in unit tests.

The simulator is not imported here: ``bench_render`` is given the factory of simulated flights
(``companion.cli.sim.scenario``), the one place where the product reaches the simulator.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, cast

import cv2
import numpy as np

from companion.config import Config, TerrainName
from companion.offline import peak_rss_mb


@dataclass(frozen=True, slots=True)
class RenderBench:
    """Per-terrain rendering figures: frame times [ms] and frames per second."""

    terrain: str
    frames: int
    median_ms: float
    p99_ms: float
    fps_median: float


def machine_description() -> str:
    """One line naming the machine the figures were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def bench_render(
    cfg: Config, terrains: list[str], frames: int, scenario: Callable[[Config], Any]
) -> dict[str, Any]:
    """Render ``frames`` frames of a lawnmower flight on each terrain on one core; the flight
    of a config is ``scenario(cfg)`` (its ``renderer.render_at`` and ``trajectory`` are used).

    The first frame (numba compilation, texture loading) is excluded. Motion blur off, live
    laser marks and noise on: the default dataset settings.
    """
    cv2.setNumThreads(1)
    results: list[RenderBench] = []
    for terrain in terrains:
        sitl = replace(
            cfg.sitl,
            terrain=cast(TerrainName, terrain),
            trajectory="lawnmower",
            seconds=max(frames / cfg.camera.rate_hz + 1.0, 2.0),
        )
        flight = scenario(replace(cfg, sitl=sitl))
        flight.renderer.render_at(flight.trajectory, 0.0, 0)  # warm-up
        times = []
        for seq in range(1, frames + 1):
            t_s = seq / cfg.camera.rate_hz
            t0 = time.perf_counter()
            flight.renderer.render_at(flight.trajectory, t_s, seq)
            times.append(time.perf_counter() - t0)
        ms = np.asarray(times) * 1e3
        med = float(np.median(ms))
        results.append(
            RenderBench(terrain, frames, med, float(np.percentile(ms, 99)), 1000.0 / med)
        )
    rss_mb = peak_rss_mb()
    return {
        "machine": machine_description(),
        "width": cfg.camera.width,
        "height": cfg.camera.height,
        "results": results,
        "peak_rss_mb": rss_mb,
    }


def format_render_report(report: dict[str, Any]) -> str:
    """Markdown table of :func:`bench_render`'s figures."""
    lines = [
        f"machine: {report['machine']}",
        f"image: {report['width']}x{report['height']}, one core, peak RSS "
        f"{report['peak_rss_mb']:.0f} MB",
        "",
        "| terrain | frames | median ms | p99 ms | fps (median) |",
        "|---|---|---|---|---|",
    ]
    for r in report["results"]:
        lines.append(
            f"| {r.terrain} | {r.frames} | {r.median_ms:.1f} | {r.p99_ms:.1f} | "
            f"{r.fps_median:.1f} |"
        )
    return "\n".join(lines)
