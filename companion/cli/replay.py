"""``companion replay REC... --json OUT.json`` (flight recordings through this version, each
with its own calibration and options or with an override file laid over them) and
``companion compare A.json B.json`` (what changed between two replays). The work is in
``companion.replay`` and ``companion.replay_compare``; docs/dataset.md, "Replaying last
week's flights".
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from companion.cli.common import EXIT_OK, EXIT_PROBLEMS, progress


def _summary(entry: dict[str, Any]) -> str:
    """One line per recording: its frames, poses, CPU, and against what flew and the truth."""
    if "error" in entry:
        return f"{entry['name']}: FAILED ({entry['kind']}): {entry['error']}"
    m = entry["metrics"]
    parts = [
        f"{m['frames']} frames",
        f"{m['poses']} poses",
        f"tracked {100.0 * (m['tracked_fraction'] or 0.0):.1f} %",
        f"{m['vo_resets']} VO resets",
    ]
    if m["cpu_ms_median"] is not None:
        parts.append(f"CPU {m['cpu_ms_median']:.1f} ms median, p99 {m['cpu_ms_p99']:.1f} ms")
    if "identical" in m:
        parts.append(
            "identical to what flew"
            if m["identical"]
            else f"vs what flew: max {m['position_diff_max_m'] or 0.0:.3g} m, "
            f"yaw {m['yaw_diff_max_deg'] or 0.0:.3g} deg"
            + (
                f", {m['published_missing']} of {m['published_poses']} sent poses not replayed"
                if m["published_missing"]
                else ""
            )
        )
    if m.get("ate_m") is not None:
        pct = m.get("ate_pct_path")
        parts.append(f"ATE {m['ate_m']:.3f} m" + (f" ({pct:.2f} % of path)" if pct else ""))
    return f"{entry['name']}: " + ", ".join(parts)


class KltFloorBeside:
    """The KLT floor of ``companion bench vo`` beside the replay (``companion.bench_vo``):
    per frame one pyramidal KLT of the frame before's features. Both sides in CPU time
    (``time.process_time``, as the replay's CPU per frame; ``bench vo``'s wall times moved
    the ratio from 3.8 to 4.8 between two replays of one recording on a loaded machine):
    ``klt_floor_ms``, the floor's median, and ``frame_to_floor``, the median CPU of the
    tracked frames over it, a figure that moves less from one machine to another than
    milliseconds do."""

    def __init__(self) -> None:
        self.floor: Any = None
        self.cpu_ms: list[float] = []

    def start(self, config: Any) -> None:
        from companion.bench_vo import KltFloor

        self.floor = KltFloor(config.vo.klt_window_px, config.vo.klt_levels)
        self.cpu_ms = []

    def __call__(self, frame: Any, pipe: Any) -> None:
        timed = len(self.floor.ms)
        t0 = time.process_time()
        self.floor(frame, pipe)
        if len(self.floor.ms) > timed:  # it tracked the frame before's features
            self.cpu_ms.append((time.process_time() - t0) * 1e3)

    def metrics(self, run: Any, cpu_ms: Sequence[float]) -> dict[str, Any]:
        import numpy as np

        from companion.bench_vo import floor_ratios

        frame_ms = np.asarray(cpu_ms)[run.tracking_mask()]
        if not len(frame_ms) or not self.cpu_ms:
            return {"klt_floor_ms": None, "frame_to_floor": None}
        r = floor_ratios(self.cpu_ms, frame_ms, [])
        return {"klt_floor_ms": r.floor_ms, "frame_to_floor": r.frame_ratio}


def cmd_replay(args: argparse.Namespace) -> int:
    """Replay every recording; a recording that fails to open or crashes mid-replay gets an
    entry with its error and the others go on (exit 1 when any failed). A bad override is a
    config error naming its key (exit 2) before any recording is read."""
    from companion.replay import read_override, replay_document, replay_failed, replay_recording

    override = read_override(args.config) if args.config is not None else None

    def bar(total: int, label: str) -> Any:
        return progress(total, label, not args.no_progress)

    entries: list[dict[str, Any]] = []
    for rec in args.recordings:
        try:
            entry = replay_recording(rec, override, bar, KltFloorBeside())
        except KeyboardInterrupt:
            raise
        except Exception as e:  # this recording's failure, not the others'
            entry = replay_failed(rec, e)
        entries.append(entry)
        print(_summary(entry), flush=True)
    doc = replay_document(entries, override)
    args.json_out.parent.mkdir(parents=True, exist_ok=True)
    args.json_out.write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")
    print(f"replay of {len(entries)} recording(s), {doc['failed']} failed: {args.json_out}")
    return EXIT_PROBLEMS if doc["failed"] else EXIT_OK


def cmd_compare(args: argparse.Namespace) -> int:
    """Compare two replay files; exit 0 when both parse (1 with --fail-if-worse when a
    metric or a recording got worse; 2 when a file is not a replay file)."""
    from companion.replay_compare import compare, compare_text, read_replay

    result = compare(read_replay(args.a), read_replay(args.b))
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print("\n".join(compare_text(result, show_same=args.all)))
    if args.fail_if_worse and result["worse"]:
        if not args.json:
            print(f"compare: {result['worse']} worse", file=sys.stderr)
        return EXIT_PROBLEMS
    return EXIT_OK


def add_replay(sub: Any) -> None:
    """``companion replay``."""
    p = sub.add_parser("replay", help="re-run flight recordings through this version")
    p.add_argument(
        "recordings", type=Path, nargs="+", metavar="REC", help="recording folders (our format)"
    )
    p.add_argument(
        "--config",
        type=Path,
        metavar="OVERRIDE.toml",
        help="[vo] [scale] [attitude] [dpose] keys laid over each recording's own "
        "(default: each recording's own options; the calibration is always its own)",
    )
    p.add_argument(
        "--json",
        dest="json_out",
        type=Path,
        required=True,
        metavar="OUT.json",
        help="where to write the metrics per recording (for `companion compare`)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=cmd_replay)


def add_compare(sub: Any) -> None:
    """``companion compare``."""
    p = sub.add_parser("compare", help="what changed between two replays (companion replay)")
    p.add_argument("a", type=Path, metavar="A.json", help="the replay before")
    p.add_argument("b", type=Path, metavar="B.json", help="the replay after")
    p.add_argument("--json", action="store_true", help="the comparison as JSON on stdout")
    p.add_argument("--all", action="store_true", help="list the metrics that stayed the same too")
    p.add_argument(
        "--fail-if-worse",
        action="store_true",
        help="exit 1 when a metric or a recording got worse (for CI)",
    )
    p.set_defaults(func=cmd_compare)
