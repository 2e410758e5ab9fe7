"""The tables of docs/RESULTS.md as batches: per table, its marker name, the tasks whose
results it is made of, and which renderer turns them into Markdown (the renderers are in
companion/cli/results.py: they use companion.reporting).

The flights are those of the Makefile's former loops (``make results``, ``results-attitude``,
``results-dpose``, ``results-real``), one task per ``companion eval`` it ran.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from companion.batch.spec import Task, flight, sequence, sim_eval

TERRAINS = ("hills", "urban", "flat", "slope")
TRAJECTORIES = ("lawnmower", "figure8")
SEEDS = (1, 2, 3)
SECONDS = 60.0
VO_GROUPS = (("hills", "lawnmower"), ("urban", "figure8"))
ATTITUDE_TERRAINS = ("flat", "hills", "urban", "slope")
DPOSE_TERRAINS = ("flat", "hills", "slope")
REAL_FB_SEQUENCES = ("rislab_downward", "tum_fr1_rpy")
REAL_FB_CONFIG = "config/real_camera.toml"
CIRCLE_SECONDS = 600.0  # the roll/pitch drift flight
PAD_CONFIG = "config/pad.toml"
PAD_SEEDS = (1, 2, 3, 4, 5)
TAKEOFF = ("--phases", "--takeoff-landing")
HARSH = "config/harsh.toml"


class GroundRow(NamedTuple):
    """A row group of the from-the-ground-up table (issue 18): its label, the flight and the
    seeds it is flown with; ``flags`` after ``--seed``, ``config`` a TOML file or None."""

    label: str
    terrain: str
    trajectory: str
    seeds: tuple[int, ...]
    flags: tuple[str, ...]
    config: str | None = None


AIR = ("--phases", "--altitude")  # from the air: no take-off, at this height [m]
GROUND_FLIGHTS = (
    GroundRow("hills lawnmower, take-off & landing", "hills", "lawnmower", SEEDS, TAKEOFF),
    GroundRow("hills lawnmower, harsh sensors", "hills", "lawnmower", SEEDS, TAKEOFF, HARSH),
    GroundRow("urban figure8, take-off & landing", "urban", "figure8", SEEDS, TAKEOFF),
    GroundRow("urban figure8, harsh sensors", "urban", "figure8", SEEDS, TAKEOFF, HARSH),
    GroundRow(
        "urban lawnmower at 3.5 m (from the air)", "urban", "lawnmower", SEEDS, (*AIR, "3.5")
    ),
    GroundRow(
        "hills lawnmower at 12 m/s, take-off & landing",
        "hills",
        "lawnmower",
        SEEDS,
        (*TAKEOFF, "--speed", "12"),
    ),
    GroundRow(
        "urban figure8 at 12 m/s, take-off & landing",
        "urban",
        "figure8",
        (1,),
        (*TAKEOFF, "--speed", "12"),
    ),
    GroundRow(
        "urban lawnmower at 12 m/s, 4 m (from the air)",
        "urban",
        "lawnmower",
        (1,),
        (*AIR, "4", "--speed", "12"),
    ),
)


@dataclass(frozen=True)
class TablePlan:
    """One table of docs/RESULTS.md: ``name`` (its marker ``<!-- results:NAME -->``), what it
    shows, its tasks and its renderer; ``skipped``: why it cannot be made here (else empty)."""

    name: str
    title: str
    tasks: tuple[Task, ...]
    render: str
    skipped: str = ""


def scale_name(terrain: str, trajectory: str, seed: int) -> str:
    """A metric-scale flight's folder: TERRAIN-TRAJECTORY-SEED (``companion report`` groups
    by it)."""
    return f"{terrain}-{trajectory}-{seed}"


def plans(real_data: Path | None, real_why: str = "") -> dict[str, TablePlan]:
    """Every table, by marker name. ``real_data``: the folder of the rebuilt real sequences
    (one dataset folder each), or None with ``real_why`` saying why they are not here."""
    out: list[TablePlan] = []
    vo = tuple(
        flight(f"vo-{t}-{tr}-{s}", t, tr, s, SECONDS, ("--methods", "vo"))
        for t, tr in VO_GROUPS
        for s in SEEDS
    )
    out.append(TablePlan("vo", "Visual odometry (issue 3)", vo, "vo"))
    for t in TERRAINS:
        for tr in TRAJECTORIES:
            tasks = tuple(
                flight(scale_name(t, tr, s), t, tr, s, SECONDS, ("--methods", "all")) for s in SEEDS
            )
            out.append(TablePlan(f"scale-{t}-{tr}", f"Metric scale, {t} / {tr}", tasks, "scale"))
    study = tuple(
        flight(f"study-{t}", t, tr, 1, SECONDS, ("--methods", "all", "--sensor-study"))
        for t, tr in VO_GROUPS
    )
    out.append(TablePlan("sensor-study", "Number of sensors", study, "sensors"))
    names = sorted(p.name for p in real_data.iterdir() if p.is_dir()) if real_data else []
    real = tuple(sequence(f"real/{n}", (real_data / n).resolve()) for n in names if real_data)
    fb = tuple(
        sequence(f"real-fb/{n}", (real_data / n).resolve(), config=REAL_FB_CONFIG)
        for n in REAL_FB_SEQUENCES
        if real_data and n in names
    )
    why = "" if real_data else real_why or "the real sequences are not rebuilt"
    out.append(TablePlan("real", "Real sequences", real, "real", why))
    out.append(TablePlan("real-fb", "Real sequences, KLT checked back", fb, "real", why))
    attitude = tuple(
        flight(f"attitude-{t}", t, "lawnmower", 1, SECONDS, ("--attitude", "--spacing", "0.5"))
        for t in ATTITUDE_TERRAINS
    )
    out.append(TablePlan("attitude", "Roll and pitch (issue 5)", attitude, "attitude"))
    study_flags = ("--attitude", "--spacing", "0.5", "--study")
    a_study = flight("attitude-study", "flat", "lawnmower", 1, SECONDS, study_flags)
    out.append(TablePlan("attitude-study", "Roll/pitch studies", (a_study,), "attitude-study"))
    circle = flight(
        "attitude-circle", "hills", "circle", 1, CIRCLE_SECONDS, ("--attitude", "--spacing", "0.5")
    )
    out.append(TablePlan("attitude-circle", "Roll/pitch, 10 minutes", (circle,), "attitude-long"))
    dpose = tuple(
        sim_eval(f"dpose-{t}", ("--dpose", "--terrain", t, "--seconds", f"{SECONDS:g}"))
        for t in DPOSE_TERRAINS
    )
    out.append(TablePlan("dpose", "d-Pose (issue 6)", dpose, "dpose"))
    rnd = sim_eval("dpose-random", ("--dpose", "--random", "10000"))
    out.append(TablePlan("dpose-random", "d-Pose, random poses", (rnd,), "dpose-random"))
    out.append(TablePlan("ground", "From the ground up (issue 18)", ground_tasks(), "ground"))
    pad = tuple(
        sim_eval(f"pad-{s}", ("--phases", "--seed", str(s)), config=PAD_CONFIG) for s in PAD_SEEDS
    )
    out.append(TablePlan("pad", "Return over the pad (issue 18)", pad, "pad"))
    return {p.name: p for p in out}


def ground_tasks() -> tuple[Task, ...]:
    """The flights of GROUND_FLIGHTS, named ``ground-<row>-<seed>`` (row: its index)."""
    return tuple(
        flight(f"ground-{i}-{s}", g.terrain, g.trajectory, s, SECONDS, g.flags, g.config)
        for i, g in enumerate(GROUND_FLIGHTS)
        for s in g.seeds
    )


def table_names() -> list[str]:
    """The marker names of every table ``companion results`` makes."""
    return list(plans(None))
