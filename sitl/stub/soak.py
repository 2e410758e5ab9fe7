"""The soak benchmark: the service as its own process against the SITL autopilot for a long
flight (``companion bench soak --minutes 30``), its memory sampled from /proc.

A 30-minute flight has 54,000 camera frames, too many to render ahead (50 GB) and too slow to
render live on a small machine without the renderer taking the service's CPU. The soak
therefore flies the circle trajectory at a speed that makes one lap a whole number of camera
frames, renders one lap (after the start transient), and the SITL camera repeats it: the
flight is exactly periodic there, so every repeated frame is the true image at its time, and
the autopilot's truth, ranges and attitude stay those of the real flight.

Measured: the service's resident memory every ``sample_s`` (growth = the last ten minutes'
maximum minus the value after the warm-up), what it received, processed, dropped and
published (its exit report), and what the autopilot received (rate, ATE per reset segment).
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config, load_config
from companion.sitl.stub.autopilot import SimAutopilot
from companion.sitl.stub.options import AutopilotOptions
from companion.sitl.world.trajectory import pattern_length_m

LAP_START_S = 8.0  # the loop starts this long into the flight (after the smoothed start)


@dataclass(frozen=True, slots=True)
class SoakPlan:
    """A periodic circle flight: its speed, and the camera frames that repeat."""

    speed_m_s: float
    loop_from_frame: int
    loop_frames: int


def plan(cfg: Config, nominal_speed_m_s: float = 3.0) -> SoakPlan:
    """The circle speed closest to ``nominal_speed_m_s`` at which one lap is a whole number
    of camera frames."""
    lap_m = pattern_length_m("circle", nominal_speed_m_s)
    rate = cfg.camera.rate_hz
    frames = round(lap_m / nominal_speed_m_s * rate)
    return SoakPlan(lap_m / (frames / rate), round(LAP_START_S * rate), frames)


def rss_mb(pid: int) -> float | None:
    """Resident set size of a process [MB] (None once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def run_soak(
    minutes: float, out: Path, config: str | None = "config/sitl.toml", sample_s: float = 10.0
) -> dict[str, Any]:
    """Fly ``minutes`` of soak; writes soak.json and rss.csv to ``out`` and returns the
    figures."""
    out.mkdir(parents=True, exist_ok=True)
    base = load_config(config)
    p = plan(base)
    seconds = minutes * 60.0 + LAP_START_S
    cfg = load_config(
        config,
        {"sitl": {"trajectory": "circle", "seconds": seconds, "speed_m_s": p.speed_m_s}},
    )
    opts = AutopilotOptions(
        prerender=True, loop_from_frame=p.loop_from_frame, loop_frames=p.loop_frames
    )
    stub = SimAutopilot(cfg, opts)
    cmd = [sys.executable, "-m", "companion.cli", "run", "--report", str(out / "service.json")]
    if config:
        cmd += ["--config", config]
    log = (out / "service.log").open("w")
    service = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log)
    samples: list[tuple[float, float]] = []

    async def fly() -> dict[str, Any]:
        task = asyncio.create_task(stub.run(out / "autopilot"))
        while not task.done():
            rss_mb_now = rss_mb(service.pid)
            t_flight_s = stub.t_sim_of_mono(time.monotonic_ns())
            if rss_mb_now is not None and t_flight_s >= 0:
                samples.append((t_flight_s, rss_mb_now))
            await asyncio.wait({task}, timeout=sample_s)
        return await task

    try:
        report = asyncio.run(fly())
    finally:
        service.terminate()
        rc = service.wait(30)
        log.close()
    svc = json.loads((out / "service.json").read_text()) if (out / "service.json").exists() else {}
    times_s = np.array([s[0] for s in samples])
    series_mb = np.array([s[1] for s in samples])
    warm = series_mb[times_s >= 120.0]
    last = series_mb[times_s >= times_s[-1] - 600.0] if len(times_s) else series_mb
    result: dict[str, Any] = {
        "minutes": minutes,
        "speed_m_s": p.speed_m_s,
        "lap_frames": p.loop_frames,
        "service_exit_code": rc,
        "rss_mb_after_warmup": float(warm[0]) if len(warm) else None,
        "rss_mb_max_last_10_min": float(last.max()) if len(last) else None,
        "rss_mb_max": float(series_mb.max()) if len(series_mb) else None,
        "autopilot": {k: v for k, v in report.items() if k != "faults"},
        "service": {k: svc.get(k) for k in (
            "frames_in", "frames_dropped", "frames_processed", "published", "not_published",
            "stale", "pipeline_errors", "publish_rate_hz", "latency_ms_p50", "latency_ms_p99",
            "vo_resets", "link", "warnings",
        )},
    }  # fmt: skip
    if result["rss_mb_after_warmup"] is not None and result["rss_mb_max_last_10_min"] is not None:
        result["rss_growth_mb"] = result["rss_mb_max_last_10_min"] - result["rss_mb_after_warmup"]
    (out / "rss.csv").write_text(
        "t_flight_s,rss_mb\n"
        + "".join(f"{t:.1f},{m:.1f}\n" for t, m in zip(times_s, series_mb, strict=True))
    )
    (out / "soak.json").write_text(json.dumps(result, indent=2, default=str) + "\n")
    return result
