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
REALISTIC = "config/realistic.toml"
# the from-the-ground-up rows flown again under realistic.toml, 3 seeds each (issue "A
# simulator as hard as reality"): the harsh-sensor rows are left out, realistic.toml's own
# distance sensors are TFmini-class (outliers on edges and water, a bias, the blind zone)
REALISTIC_GROUND_ROWS = (0, 2, 4, 5, 6, 7)
# the simulator's effects one at a time, then all of them (issue "A simulator as hard as
# reality"): (the flight's name, the row's label); the config file: effect_config(name)
EFFECT_ROWS = (
    ("ideal", "none (ideal)"),
    ("rolling_shutter", "rolling shutter 20 ms, the VO not told"),
    ("rolling_shutter_vo", "rolling shutter 20 ms, the VO told the readout"),
    ("exposure", "auto-exposure, drift, clouds, vignetting; raw KLT"),
    ("exposure_vo", "the same, KLT on normalised images"),
    ("lens", "lens: f +1 %, pp (3, -2) px, k1 +0.02, not learned"),
    ("lens_k1_checked", "the same, the file's k1 raised by the lens check's +0.021"),
    ("lens_learn", "the same, learned in flight (`[vo] learn_lens`)"),
    ("motion_blur", "motion blur, 8 ms exposure"),
    ("mount", "mount 1 deg, not learned"),
    ("tiles", "floor tiles, 0.5 m period"),
    ("checkerboard", "checkerboard, 0.3 m squares"),
    ("concrete", "concrete, low texture"),
    ("specular", "water over 15 % of the ground"),
    ("carpet", "carpet, low texture"),
    ("parking", "parking lot lines"),
    ("shadow", "the vehicle's shadow"),
    ("downwash", "downwash 0.01 m"),
    ("rangefinder", "TFmini-class sensors"),
    ("realistic", "**all of config/realistic.toml**"),
    ("realistic_learn", "all of it, the lens learned in flight (`[vo] learn_lens`)"),
)
NEEDS_REAL = ("real", "real-fb", "sim-vs-real")  # the tables made of the real sequences
EFFECTS_FLIGHT = ("hills", "lawnmower")
# each real sequence beside its simulated look-alike (config/like_real/): (real, look-alike)
LIKE_PAIRS = (("tum_fr1_rpy", "handheld_pan"), ("rislab_downward", "downward_checkerboard"))


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
    out.append(TablePlan("effects", "Each effect alone, and all of them", effect_tasks(), "rows"))
    out.append(
        TablePlan("air-realistic", "From the air, realistic.toml", air_realistic_tasks(), "air")
    )
    out.append(
        TablePlan(
            "ground-realistic",
            "From the ground up, realistic.toml",
            ground_realistic_tasks(),
            "ground",
        )
    )
    like = tuple(
        sim_eval(f"like/{sim}-{s}", ("--methods", "all", "--seed", str(s)), config=like_config(sim))
        for _, sim in LIKE_PAIRS
        for s in SEEDS
    )
    their_real = tuple(t for t in real if t.name in {f"real/{r}" for r, _ in LIKE_PAIRS})
    missing = [r for r, _ in LIKE_PAIRS if real_data and r not in names]
    like_why = why or (f"{', '.join(missing)} not among the rebuilt sequences" if missing else "")
    out.append(
        TablePlan(
            "sim-vs-real",
            "The simulator against reality",
            like + their_real,
            "sim-vs-real",
            like_why,
        )
    )
    return {p.name: p for p in out}


def like_config(sim: str) -> str:
    """The config file of a look-alike flight."""
    return f"config/like_real/{sim}.toml"


def effect_config(name: str) -> str | None:
    """The config file of an effect's flight: none for the ideal world, realistic.toml for
    all of them, else config/effects/NAME.toml."""
    if name == "ideal":
        return None
    return "config/realistic.toml" if name == "realistic" else f"config/effects/{name}.toml"


def effect_tasks() -> tuple[Task, ...]:
    """The flights of EFFECT_ROWS, named ``effects/<name>-<seed>``: hills lawnmower, 60 s,
    every method."""
    t, tr = EFFECTS_FLIGHT
    return tuple(
        flight(f"effects/{name}-{s}", t, tr, s, SECONDS, ("--methods", "all"), effect_config(name))
        for name, _ in EFFECT_ROWS
        for s in SEEDS
    )


def ground_tasks() -> tuple[Task, ...]:
    """The flights of GROUND_FLIGHTS, named ``ground-<row>-<seed>`` (row: its index)."""
    return tuple(
        flight(f"ground-{i}-{s}", g.terrain, g.trajectory, s, SECONDS, g.flags, g.config)
        for i, g in enumerate(GROUND_FLIGHTS)
        for s in g.seeds
    )


def air_realistic_tasks() -> tuple[Task, ...]:
    """The metric-scale flights of every terrain and trajectory under realistic.toml, named
    ``air-realistic/TERRAIN-TRAJECTORY-SEED``: 60 s, every method."""
    return tuple(
        flight(
            f"air-realistic/{scale_name(t, tr, s)}",
            t,
            tr,
            s,
            SECONDS,
            ("--methods", "all"),
            REALISTIC,
        )
        for t in TERRAINS
        for tr in TRAJECTORIES
        for s in SEEDS
    )


def ground_realistic_tasks() -> tuple[Task, ...]:
    """The GROUND_FLIGHTS rows of REALISTIC_GROUND_ROWS under realistic.toml, 3 seeds each,
    named ``ground-realistic/ground-<row>-<seed>`` (row: its index in GROUND_FLIGHTS)."""
    rows = [(i, GROUND_FLIGHTS[i]) for i in REALISTIC_GROUND_ROWS]
    return tuple(
        flight(
            f"ground-realistic/ground-{i}-{s}",
            g.terrain,
            g.trajectory,
            s,
            SECONDS,
            g.flags,
            REALISTIC,
        )
        for i, g in rows
        for s in SEEDS
    )


def table_names() -> list[str]:
    """The marker names of every table ``companion results`` makes."""
    return list(plans(None))
