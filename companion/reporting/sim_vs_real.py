"""Does the simulator predict reality? A real sequence's errors beside those of its simulated
look-alike (config/like_real/: the same kind of motion, camera and ground, every camera effect
of config/realistic.toml), as a Markdown table and a bar plot (docs/RESULTS.md, "The simulator
against reality").

Both sides are `companion eval ... --methods all` folders: the real one a dataset without a
world (its scale_metrics.json a document with ``methods``, ``vo`` and ``tracks``), the
simulated one NAME-SEED folders of a simulated flight (a list of methods, eval.json's
``tracks`` and ``vo_resets``), averaged over the seeds. Compared on the published method
(M-MSCwK): its metric ATE after an SE(3) alignment [m] and as % of the path, its ratio to the
best constant position, and the VO's resets. The issue's test: the simulated ATE within 2x of
the real one (a ratio sim / real in [0.5, 2]).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.reporting.rows import PUBLISHED, name_and_seed

WITHIN = 2.0  # the simulated error within this factor of the real one


@dataclass(frozen=True)
class Errors:
    """One side of a pair: ``runs`` folders (seeds) behind it, the published method's ATE [m]
    and [% of path] and its ratio to the best constant position (None: not recorded), over the
    runs that have an estimate (``no_estimate`` runs have none: the VO never gave a pose), and
    the VO's resets (mean over all the runs; None: not recorded)."""

    runs: int
    ate_m: float
    ate_pct: float
    ratio_to_constant: float | None
    resets: float | None
    no_estimate: int = 0  # runs (seeds) in which the published method never had a pose


def _json(path: Path) -> Any:
    return json.loads(path.read_text())


def real_errors(folder: Path) -> Errors:
    """The errors of a real sequence's evaluation folder (ValueError: not one, or no
    estimate)."""
    doc = _json(folder / "scale_metrics.json")
    if not isinstance(doc, dict):
        raise ValueError(f"{folder}: a simulated flight's folder, not a real sequence's")
    ours = {m["method"]: m for m in doc.get("methods", [])}.get(PUBLISHED) or {}
    if ours.get("ate_se3_m") is None:
        raise ValueError(f"{folder}: {PUBLISHED} has no estimate")
    track = (doc.get("tracks") or {}).get(PUBLISHED) or {}
    resets = (doc.get("vo") or {}).get("resets")
    return Errors(
        1,
        float(ours["ate_se3_m"]),
        float(ours["ate_se3_pct"]),
        track.get("ratio_to_mean"),
        None if resets is None else float(resets),
    )


def sim_errors(folders: list[Path]) -> Errors:
    """The mean errors of a simulated flight's NAME-SEED folders (ValueError: none)."""
    if not folders:
        raise ValueError("no simulated flight")
    ate_m, ate_pct = [], []
    ratios: list[float | None] = []
    resets: list[float | None] = []
    for d in folders:
        methods = {m["method"]: m for m in _json(d / "scale_metrics.json")}
        honest = _json(d / "eval.json") if (d / "eval.json").exists() else {}
        resets.append(honest.get("vo_resets"))
        if PUBLISHED not in methods:
            continue  # no pose in the whole flight: no error to average
        ate_m.append(float(methods[PUBLISHED]["ate_m"]))
        ate_pct.append(float(methods[PUBLISHED]["ate_pct"]))
        ratios.append(((honest.get("tracks") or {}).get(PUBLISHED) or {}).get("ratio_to_mean"))
    missing = len(folders) - len(ate_m)
    if not ate_m:
        raise ValueError(f"{PUBLISHED} has no estimate in any of {len(folders)} flights")
    mean_m, mean_pct = float(np.mean(ate_m)), float(np.mean(ate_pct))
    return Errors(len(folders), mean_m, mean_pct, _mean(ratios), _mean(resets), missing)


def _mean(values: list[float | None]) -> float | None:
    """The mean of ``values``, None when one of them is missing."""
    known = [v for v in values if v is not None]
    return float(np.mean(known)) if known and len(known) == len(values) else None


def seed_folders(prefix: Path) -> list[Path]:
    """The folders PREFIX-SEED beside ``prefix`` holding an evaluation, seeds ascending."""
    found = []
    for d in prefix.parent.glob(f"{prefix.name}-*"):
        key = name_and_seed(d)
        if key is not None and key[0] == prefix.name and (d / "scale_metrics.json").exists():
            found.append((key[1], d))
    return [d for _, d in sorted(found)]


def _opt(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def comparison_table(pairs: list[tuple[str, Errors, Errors]]) -> str:
    """Markdown: per pair (label, simulated, real) the published method's ATE on each side,
    the ratio sim / real of the ATE as % of the path and whether it is within WITHIN x."""
    out = [
        f"| motion | simulated {PUBLISHED} ATE (seeds) | real {PUBLISHED} ATE | sim / real "
        f"| within {WITHIN:g}x | ratio to best constant, sim / real | VO resets, sim / real |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, sim, real in pairs:
        ratio = sim.ate_pct / real.ate_pct if real.ate_pct > 0 else float("inf")
        within = "yes" if 1 / WITHIN <= ratio <= WITHIN else "NO"
        out.append(
            f"| {label} | {sim.ate_m:.3f} m = {sim.ate_pct:.3f} % ({_runs(sim)}) "
            f"| {real.ate_m:.3f} m = {real.ate_pct:.3f} % | {ratio:.3g} | {within} "
            f"| {_opt(sim.ratio_to_constant, '.3f')} / {_opt(real.ratio_to_constant, '.3f')} "
            f"| {_opt(sim.resets, '.1f')} / {_opt(real.resets, '.0f')} |"
        )
    return "\n".join(out)


def _runs(side: Errors) -> str:
    """How many runs an error is the mean of: "3", or "2 of 3; 1 without a pose"."""
    if not side.no_estimate:
        return str(side.runs)
    return f"{side.runs - side.no_estimate} of {side.runs}; {side.no_estimate} without a pose"


def comparison_plot(pairs: list[tuple[str, Errors, Errors]], path: Path) -> Path:
    """A PNG of the pairs side by side: the ATE as % of the path, with the real one's WITHIN x
    band (log scale when the values span more than 20x), and the resets."""
    from companion.reporting.figures import pyplot, save

    plt = pyplot()
    fig, (ax_ate, ax_resets) = plt.subplots(1, 2, figsize=(10, 4.4))
    x = np.arange(len(pairs))
    width = 0.38
    labels = [p[0].replace(" / ", "\n") for p in pairs]
    sim_pct = np.array([p[1].ate_pct for p in pairs])
    real_pct = np.array([p[2].ate_pct for p in pairs])
    ax_ate.bar(x - width / 2, sim_pct, width, label="simulated (realistic)", color="tab:blue")
    ax_ate.bar(x + width / 2, real_pct, width, label="real", color="tab:orange")
    band = [real_pct - real_pct / WITHIN, real_pct * WITHIN - real_pct]
    ax_ate.errorbar(
        x + width / 2,
        real_pct,
        yerr=band,
        fmt="none",
        ecolor="black",
        capsize=5,
        label=f"real / {WITHIN:g} .. real x {WITHIN:g}",
    )
    values = np.concatenate([sim_pct, real_pct])
    if values.min() > 0 and values.max() / values.min() > 20:
        ax_ate.set_yscale("log")
    else:
        ax_ate.set_ylim(0, 1.5 * max(values.max(), (real_pct * WITHIN).max()))  # room: legend
    ax_ate.set_ylabel(f"{PUBLISHED} metric ATE, % of path")
    ax_resets.bar(x - width / 2, [p[1].resets or 0.0 for p in pairs], width, color="tab:blue")
    ax_resets.bar(x + width / 2, [p[2].resets or 0.0 for p in pairs], width, color="tab:orange")
    ax_resets.set_ylabel("VO resets")
    for ax in (ax_ate, ax_resets):
        ax.set_xticks(x, labels, fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    ax_ate.legend(fontsize=8, loc="upper left")
    fig.suptitle("The simulator against reality: each real sequence beside its look-alike")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    return save(plt, fig, path)
