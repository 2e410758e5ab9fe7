"""The render benchmark's figures (companion/bench.py): what it times and how it reports, on a
renderer whose cost is known (the figures themselves go to docs/BENCHMARKS.md, never asserted)."""

from __future__ import annotations

import time
from types import SimpleNamespace
from typing import Any

from companion.bench import bench_render, format_render_report, machine_description
from companion.config import Config, load_config


class CountingRenderer:
    """A renderer that records which frames it was asked for and sleeps a fixed time each."""

    def __init__(self, cost_s: float) -> None:
        self.cost_s = cost_s
        self.calls: list[tuple[float, int]] = []

    def render_at(self, trajectory: Any, t_s: float, seq: int) -> None:
        self.calls.append((t_s, seq))
        time.sleep(self.cost_s)


def test_render_bench_times_every_frame_but_the_warm_up_and_reports_each_terrain() -> None:
    cfg = load_config(None)
    flights: list[tuple[Config, CountingRenderer]] = []

    def scenario(c: Config) -> Any:
        renderer = CountingRenderer(0.002)
        flights.append((c, renderer))
        return SimpleNamespace(renderer=renderer, trajectory=None)

    report = bench_render(cfg, ["flat", "hills"], 5, scenario)
    assert [c.sitl.terrain for c, _ in flights] == ["flat", "hills"]
    for c, renderer in flights:
        assert c.sitl.trajectory == "lawnmower"
        assert c.sitl.seconds >= 5 / cfg.camera.rate_hz  # the flight is long enough
        # the warm-up frame (seq 0) first, then the 5 timed frames at the camera's rate
        assert [seq for _, seq in renderer.calls] == [0, 1, 2, 3, 4, 5]
        assert renderer.calls[5][0] == 5 / cfg.camera.rate_hz
    rows = report["results"]
    assert [r.terrain for r in rows] == ["flat", "hills"] and all(r.frames == 5 for r in rows)
    for r in rows:  # at least the renderer's own 2 ms; the rate its inverse
        assert r.median_ms >= 2.0 and r.p99_ms >= r.median_ms
        assert abs(r.fps_median - 1000.0 / r.median_ms) < 1e-9
    assert report["peak_rss_mb"] > 0 and report["machine"] == machine_description()

    text = format_render_report(report)
    assert text.splitlines()[0] == f"machine: {report['machine']}"
    assert sum(line.startswith(("| flat |", "| hills |")) for line in text.splitlines()) == 2
