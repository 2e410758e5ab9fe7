"""``companion results`` (every table of docs/RESULTS.md from one batch, serial or on Ray)
and ``companion sweep`` (a grid of config values over datasets or flights, sorted by a
metric). The batch itself is ``companion.batch``; the tables are drawn here with
``companion.reporting`` (imported inside the functions, as in ``evaluate``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.batch import plans as plans_mod
from companion.batch.executors import EXECUTORS, Executor, make_executor
from companion.batch.plans import TablePlan
from companion.batch.results_md import machine, replace_blocks, stamp
from companion.batch.runner import BatchReport, print_failures, run_batch
from companion.batch.spec import Task
from companion.cli.common import EXIT_OK, EXIT_PROBLEMS, EXIT_USAGE
from companion.errors import BatchError

DEFAULT_OUT = Path("out") / "results"
DEFAULT_SNAPSHOTS = Path("..") / ".mirror"  # the Makefile's SNAPSHOTS
DEFAULT_MANIFEST = Path("config/real_sequences.toml")


def _refused(message: str) -> int:
    print(f"companion: usage: {message}", file=sys.stderr)
    return EXIT_USAGE


def _executor(args: argparse.Namespace) -> Executor | int:
    """The executor of --executor / --address, or exit 2 with why."""
    try:
        return make_executor(args.executor, args.address)
    except BatchError as e:
        return _refused(str(e))


# ------------------------------------------------------------------------------ results
BUILT_BY = ".built_by"  # in out/real/data: the hash of what built it (real_data)


def importers_sha256() -> str:
    """SHA-256 of what a rebuild of the real sequences depends on: the manifest and the
    importers' sources (the package's drivers/dataset/)."""
    from companion.batch.cache import package_root, sources_sha256

    h = hashlib.sha256(sources_sha256(package_root() / "drivers" / "dataset").encode())
    if DEFAULT_MANIFEST.is_file():
        h.update(DEFAULT_MANIFEST.read_bytes())
    return h.hexdigest()


def real_data(out: Path, snapshots: Path) -> tuple[Path | None, str]:
    """The rebuilt real sequences (``out/real/data``): rebuilt from ``snapshots`` (``companion
    dataset rebuild --all``) when absent or built by another manifest or importer; (None, why)
    when there is nothing to build from."""
    data = out / "real" / "data"
    stamp = importers_sha256()
    built = data / BUILT_BY
    if data.is_dir() and built.is_file() and built.read_text().strip() == stamp:
        return data, ""
    if not snapshots.is_dir():
        return None, f"no snapshots folder {snapshots} (--snapshots DIR: the git snapshots)"
    if data.is_dir():
        print(f"results: {data} was built by another importer: rebuilding", file=sys.stderr)
        shutil.rmtree(data)
    print(f"results: rebuilding the real sequences from {snapshots} into {data}", file=sys.stderr)
    cmd = [sys.executable, "-m", "companion.cli", "dataset", "rebuild", "--all"]
    proc = subprocess.run([*cmd, "--snapshots", str(snapshots), "--out", str(data)], check=False)
    if proc.returncode != 0:
        return None, f"companion dataset rebuild failed (exit {proc.returncode})"
    built.write_text(stamp + "\n")
    return data, ""


def cmd_results(args: argparse.Namespace) -> int:
    """Run the tasks of the chosen tables (all by default) through the cache, print each
    table with its stamp, and with --write replace them between their markers."""
    every = plans_mod.table_names()
    unknown = sorted(set(args.only or ()) - set(every))
    if unknown:
        return _refused(f"--only {' '.join(unknown)}: no such table (tables: {', '.join(every)})")
    chosen = list(args.only or every)
    if args.list:
        print("\n".join(chosen))
        return EXIT_OK
    if args.write is not None and not args.write.is_file():
        return _refused(f"--write {args.write}: no such file")
    out: Path = args.out
    data, why = (None, "")
    if any(n in plans_mod.NEEDS_REAL for n in chosen):
        data, why = real_data(out, args.snapshots)
    tables = {n: p for n, p in plans_mod.plans(data, why).items() if n in chosen}
    for p in tables.values():
        if p.skipped:
            print(f"results: {p.name}: skipped: {p.skipped}", file=sys.stderr)
    tasks = [t for p in tables.values() if not p.skipped for t in p.tasks]
    executor = _executor(args)
    if isinstance(executor, int):
        return executor
    try:
        report = run_batch(tasks, executor, out, args.cache)
    finally:
        executor.close()
    where = machine(Path(__file__).resolve().parents[2])
    bodies: dict[str, str] = {}
    for p in tables.values():
        if p.skipped or not p.tasks:
            continue
        if any(report.outcomes[t.name].status == "failed" for t in p.tasks):
            print(f"results: {p.name}: not drawn, a task of it failed", file=sys.stderr)
            continue
        body = RENDERERS[p.render](p, report)
        bodies[p.name] = stamp(p.name, where, args.executor) + "\n\n" + body
        print(f"<!-- results:{p.name} -->\n{bodies[p.name]}\n<!-- /results -->\n")
    if args.write is not None and bodies:
        text = args.write.read_text()
        args.write.write_text(replace_blocks(text, bodies))
        print(f"results: {len(bodies)} table(s) written in {args.write}", file=sys.stderr)
    print_failures(report, out)
    return EXIT_PROBLEMS if report.failed else EXIT_OK


def _linked(p: TablePlan, report: BatchReport) -> list[Path]:
    """The tasks' result folders seen through their names (``out/NAME``): ``companion
    report`` reads a folder's name (TERRAIN-TRAJECTORY-SEED, a sequence's name)."""
    out = []
    for t in p.tasks:
        folder = report.outcomes[t.name].folder
        if folder is None:
            raise BatchError(f"{t.name}: no result")
        out.append(folder)
    return out


def _arg(task: Task, flag: str) -> str:
    """The value of ``flag`` in a task's command line."""
    return task.argv[task.argv.index(flag) + 1]


def _json(path: Path) -> Any:
    return json.loads(path.read_text())


def render_vo(p: TablePlan, report: BatchReport) -> str:
    """The VO table (issue 3): one row per flight."""
    head = "| terrain / trajectory | seed | init after | tracking | resets | path | ATE Sim(3) "
    lines = [head + "| ATE % of path |", "|---|---|---|---|---|---|---|---|"]
    for t, d in zip(p.tasks, _linked(p, report), strict=True):
        _, terrain, traj, seed = t.name.split("-")
        m = _json(d / "metrics.json")
        lines.append(
            f"| {terrain} / {traj} | {seed} | {m['first_tracking_s']:.2f} s | "
            f"{100 * m['tracking_ratio']:.0f} % | {m['resets']} | {m['path_m']:.1f} m | "
            f"{m['ate_sim3_m']:.3f} m | {m['ate_sim3_pct']:.2f} % |"
        )
    return "\n".join(lines)


def render_scale(p: TablePlan, report: BatchReport) -> str:
    """One terrain / trajectory group of `companion report` (seed averages, who beats whom),
    without its heading."""
    from companion.reporting import summary

    text = summary(_linked(p, report))
    return "\n".join(ln for ln in text.splitlines() if not ln.startswith("### ")).strip()


def render_real(p: TablePlan, report: BatchReport) -> str:
    """The real sequences' table of `companion report`."""
    from companion.reporting import summary

    return summary(_linked(p, report)).strip()


def render_sensors(p: TablePlan, report: BatchReport) -> str:
    """M-MSC with the first k of six sensors: per flight, its scale error and metric ATE."""
    head, rule = "| sensors |", "|---|"
    by_k: dict[int, list[str]] = {}
    for t, d in zip(p.tasks, _linked(p, report), strict=True):
        flight = f"{_arg(t, '--terrain')} / {_arg(t, '--trajectory')}, seed {_arg(t, '--seed')}"
        head += f" {flight}: scale error | metric ATE |"
        rule += "---|---|"
        for r in _json(d / "scale_metrics.json"):
            if r["method"].startswith("M-MSC k="):
                by_k.setdefault(int(r["method"].split("=")[1]), []).append(
                    f" {r['scale_mean_abs_rel_pct']:.2f} % (MSE {r['scale_mse']:.2e}) | "
                    f"{r['ate_m']:.3f} m |"
                )
    lines = [head, rule] + [f"| {k} |" + "".join(cells) for k, cells in sorted(by_k.items())]
    return "\n".join(lines)


def render_attitude(p: TablePlan, report: BatchReport) -> str:
    """Roll / pitch RMSE per terrain and estimate."""
    head = "| terrain | VO alone | ranges, uncompensated | ranges, compensated (available) | "
    lines = [head + "**published** | fused, range tilts only |", "|---|---|---|---|---|---|"]
    for t, d in zip(p.tasks, _linked(p, report), strict=True):
        rows = {r["estimate"]: r for r in _json(d / "attitude_metrics.json")}
        rp = _roll_pitch(rows)
        avail = f"{100 * rows['gravity']['available']:.1f} %"
        lines.append(
            f"| {t.name.split('-', 1)[1]} | {rp('vo')} | {rp('ground')} | {rp('gravity')} "
            f"({avail}) | **{rp('fused', 3)}** | {rp('fused_ranges')} |"
        )
    return "\n".join(lines)


def _roll_pitch(rows: dict[str, Any]) -> Callable[..., str]:
    """``rp(estimate, digits)``: "roll / pitch°" of one estimate's row."""

    def rp(name: str, digits: int = 2) -> str:
        r = rows[name]
        return f"{r['roll_rmse_deg']:.{digits}f} / {r['pitch_rmse_deg']:.{digits}f}°"

    return rp


def render_attitude_study(p: TablePlan, report: BatchReport) -> str:
    """The spacing and noise studies as the command wrote them (attitude_study.md)."""
    return (_linked(p, report)[0] / "attitude_study.md").read_text().strip()


def render_dpose(p: TablePlan, report: BatchReport) -> str:
    """d-Pose and the VO per terrain and height band."""
    head = "| terrain | estimate | heights | frames | available | translation MSE | "
    head += "translation RMSE | orientation MSE | orientation RMSE |"
    lines = [head, "|---" * 9 + "|"]
    for t, d in zip(p.tasks, _linked(p, report), strict=True):
        for r in _json(d / "dpose_metrics.json"):
            lines.append(
                f"| {t.name.split('-', 1)[1]} | {r['estimate']} | {r['heights']} | "
                f"{r['frames']} | {100 * r['available']:.1f} % | {r['t_mse_m2']:.2e} m² | "
                f"{r['t_rmse_m']:.3f} m | {r['r_mse_deg2']:.3f} deg² | {r['r_rmse_deg']:.3f} deg |"
            )
    return "\n".join(lines)


def render_dpose_random(p: TablePlan, report: BatchReport) -> str:
    """The random-pose study's lines, as the command printed them."""
    text = (_linked(p, report)[0] / "stdout.txt").read_text()
    lines = [ln for ln in text.splitlines() if "random poses" in ln]
    return "```\n" + "\n".join(lines) + "\n```"


def render_attitude_long(p: TablePlan, report: BatchReport) -> str:
    """A long roll/pitch flight: every estimate's RMSE, and the RMSE of its first and last
    minute (does it drift?)."""
    head = "| estimate | roll / pitch RMSE | available | first minute | last minute |"
    lines = [head, "|---" * 5 + "|"]
    for r in _json(_linked(p, report)[0] / "attitude_metrics.json"):
        lines.append(
            f"| {r['label']} | {r['roll_rmse_deg']:.3f} / {r['pitch_rmse_deg']:.3f}° | "
            f"{100 * r['available']:.1f} % | {r['first_min_rmse_deg']:.3f}° | "
            f"{r['last_min_rmse_deg']:.3f}° |"
        )
    return "\n".join(lines)


PHASES = ("ground", "climb", "cruise", "descent", "landed")


def render_ground(p: TablePlan, report: BatchReport) -> str:
    """From the ground up: one row per flight (phases.json); a phase's RMS / max in cm, "-"
    for a phase the flight has not (a flight started in the air)."""
    head = "| flight | seed | first pose | VO resets | metric ATE | % of path | "
    lines = [head + " | ".join(PHASES) + " | end error |", "|---" * 12 + "|"]
    shown = set()
    for t, d in zip(p.tasks, _linked(p, report), strict=True):
        _, row, seed = t.name.rpartition("/")[2].split("-")
        label = "" if row in shown else plans_mod.GROUND_FLIGHTS[int(row)].label
        shown.add(row)
        m = _json(d / "phases.json")
        cells = []
        for phase in PHASES:
            ph = m["phases"].get(phase, {"frames": 0})
            cells.append(
                f"{100 * ph['rmse_m']:.1f} / {100 * ph['max_m']:.1f}" if ph["frames"] else "-"
            )
        lines.append(
            f"| {label} | {seed} | {m['first_pose_s']:.2f} s | {m['vo_resets']} | "
            f"{m['ate_m']:.3f} m | {_pct_of_path(m['ate_pct_of_path'])} | {' | '.join(cells)} | "
            f"{100 * m['end_error_m']:.1f} cm |"
        )
    return "\n".join(lines)


def _pct_of_path(value: float | None) -> str:
    """A phases.json ``ate_pct_of_path``: "-" for a path too short for one (null)."""
    return "-" if value is None else f"{value:.3f} %"


def render_pad(p: TablePlan, report: BatchReport) -> str:
    """Return over the pad: d-Pose's error from the arming pose while back over the marks."""
    head = "| seed | d-Pose armed at | poses back over the marks | RMS [cm] | max [cm] | "
    lines = [head + "the VO alone, RMS [cm] |", "|---" * 6 + "|"]
    for t, d in zip(p.tasks, _linked(p, report), strict=True):
        m = _json(d / "phases.json")
        dp = m.get("dpose")
        if dp is None or dp["published_rmse_m"] is None:
            lines.append(f"| {t.name.split('-')[1]} | not armed | 0 | - | - | - |")
            continue
        lines.append(
            f"| {t.name.split('-')[1]} | {dp['armed_s']:.2f} s | {dp['poses_in_view']} | "
            f"{100 * dp['published_rmse_m']:.2f} | {100 * dp['published_max_m']:.2f} | "
            f"{100 * dp['vo_rmse_m']:.2f} |"
        )
    return "\n".join(lines)


def render_rows(p: TablePlan, report: BatchReport) -> str:
    """One row per flight over its seeds (`companion report --rows`), labelled by
    plans.EFFECT_ROWS with the flight's config file."""
    from companion.reporting.rows import read_rows, rows_table

    labels = {}
    for name, label in plans_mod.EFFECT_ROWS:
        config = plans_mod.effect_config(name)
        labels[name] = f"{label} ({config.rpartition('/')[2] if config else 'no --config'})"
    return rows_table(read_rows(_linked(p, report)), labels)


def render_air(p: TablePlan, report: BatchReport) -> str:
    """One row per terrain / trajectory over its seeds, with the share of frames posed and
    the scale's error (`companion report --rows` in detail)."""
    from companion.reporting.rows import read_rows, rows_table

    labels = {
        f"{t}-{tr}": f"{t} / {tr}" for t in plans_mod.TERRAINS for tr in plans_mod.TRAJECTORIES
    }
    return rows_table(read_rows(_linked(p, report)), labels, detail=True)


def render_sim_vs_real(p: TablePlan, report: BatchReport) -> str:
    """Each real sequence beside its look-alike's seeds (`companion report --sim-vs-real`)."""
    from companion.reporting.sim_vs_real import comparison_table, real_errors, sim_errors

    folders = dict(zip((t.name for t in p.tasks), _linked(p, report), strict=True))
    rows = []
    for real, sim in plans_mod.LIKE_PAIRS:
        sims = [folders[f"like/{sim}-{s}"] for s in plans_mod.SEEDS]
        rows.append((f"{real} / {sim}", sim_errors(sims), real_errors(folders[f"real/{real}"])))
    return comparison_table(rows)


RENDERERS: dict[str, Callable[[TablePlan, BatchReport], str]] = {
    "vo": render_vo,
    "scale": render_scale,
    "real": render_real,
    "sensors": render_sensors,
    "attitude": render_attitude,
    "attitude-study": render_attitude_study,
    "dpose": render_dpose,
    "dpose-random": render_dpose_random,
    "attitude-long": render_attitude_long,
    "ground": render_ground,
    "pad": render_pad,
    "rows": render_rows,
    "air": render_air,
    "sim-vs-real": render_sim_vs_real,
}


# ------------------------------------------------------------------------------ sweep
def cmd_sweep(args: argparse.Namespace) -> int:
    """Every grid point on every dataset / flight, through the cache; the table sorted by
    --metric on stdout (--json: the rows as JSON)."""
    from companion.batch import sweep

    grids = [sweep.parse_grid(g) for g in args.grid]
    tasks: list[Task] = sweep.sweep_tasks(
        grids, args.datasets, args.flights, args.seconds, args.config
    )
    executor = _executor(args)
    if isinstance(executor, int):
        return executor
    try:
        report = run_batch(tasks, executor, args.out, args.cache)
    finally:
        executor.close()
    rows = []
    for t in tasks:
        o = report.outcomes[t.name]
        base = t.name.split("/")[0]
        point = t.overrides
        method = str(dict(point).get("scale.method", sweep.PUBLISHED))
        if o.folder is None:
            rows.append(sweep.SweepRow(base, point, {}, o.error))
            continue
        try:
            rows.append(sweep.SweepRow(base, point, sweep.metrics_of(o.folder, method)))
        except BatchError as e:
            rows.append(sweep.SweepRow(base, point, {}, str(e)))
    if args.json:
        ordered = sweep.sort_rows(rows, args.metric)
        doc = [
            {"input": r.input, "point": dict(r.point), "metrics": r.metrics, "error": r.error}
            for r in ordered
        ]
        print(json.dumps({"metric": args.metric, "rows": doc}, indent=2))
    else:
        print(sweep.table(rows, grids, args.metric))
    print_failures(report, args.out)
    return EXIT_PROBLEMS if report.failed else EXIT_OK


# ------------------------------------------------------------------------------ parsers
def _batch_flags(p: argparse.ArgumentParser, out: Path) -> None:
    p.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="serial",
        help="serial: one task after another here; ray: Ray tasks (local, or --address)",
    )
    p.add_argument(
        "--address",
        help="--executor ray: a Ray cluster's address, HEAD:PORT (default $RAY_ADDRESS; "
        "neither: a local Ray on this machine's cores)",
    )
    p.add_argument("--out", type=Path, default=out, help=f"result folders (default {out})")
    p.add_argument("--cache", type=Path, help="the cache of results by key (default OUT/cache)")


def add_results(sub: Any) -> None:
    """``companion results``."""
    p = sub.add_parser("results", help="regenerate the tables of docs/RESULTS.md (a batch)")
    _batch_flags(p, DEFAULT_OUT)
    p.add_argument("--only", nargs="+", metavar="NAME", help="these tables only (see --list)")
    p.add_argument("--list", action="store_true", help="list the tables' names and stop")
    p.add_argument(
        "--write",
        type=Path,
        metavar="FILE",
        help="replace the tables between their markers in FILE",
    )
    p.add_argument(
        "--snapshots",
        type=Path,
        default=DEFAULT_SNAPSHOTS,
        help=f"git snapshots of the real sequences (default {DEFAULT_SNAPSHOTS})",
    )
    p.set_defaults(func=cmd_results)


def add_sweep(sub: Any) -> None:
    """``companion sweep``."""
    from companion.batch.sweep import METRICS

    p = sub.add_parser("sweep", help="a grid of config values over datasets or flights")
    p.add_argument(
        "--grid",
        action="append",
        required=True,
        metavar="KEY=V1,V2",
        help="a config key and its values (repeat for a product: --grid vo.max_features=150,200)",
    )
    p.add_argument("--datasets", type=Path, nargs="+", default=[], help="dataset folders")
    p.add_argument("--flights", nargs="+", default=[], metavar="T-TR-S", help="simulated flights")
    p.add_argument("--seconds", type=float, default=60.0, help="--flights: their length [s]")
    p.add_argument("--config", help="a TOML config the grid is laid over (default built-in)")
    p.add_argument("--metric", choices=list(METRICS), default="metric_ate_m", help="sort by")
    p.add_argument("--json", action="store_true", help="the rows as JSON on stdout")
    _batch_flags(p, Path("out") / "sweep")
    p.set_defaults(func=cmd_sweep)
