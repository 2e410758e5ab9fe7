"""``companion eval --dpose``: d-Pose on a simulated flight over its painted marks, or over
random synthetic poses. Run from ``companion.offline.run_dpose``, metrics from
``companion.evaluation.dpose``, tables and plots from ``companion.reporting`` (offline and
reporting load the Pipeline: imported inside the commands)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from companion.cli import sim
from companion.cli.common import DPOSE_ARM_S, EXIT_OK, dpose_config, out_dir, run_name
from companion.config import Config
from companion.evaluation.dpose import armed_pattern, random_pose_study, study_bands


def eval_dpose(args: argparse.Namespace) -> int:
    """d-Pose on a SITL flight over its painted marks (spiral, 2-8 m, yaw over the full circle)
    against the VO, or (--random N) over N random synthetic poses."""
    from companion.offline import run_dpose
    from companion.reporting import write_dpose

    cfg = dpose_config(args)
    if args.random:
        return _dpose_random(cfg, args.random)
    name = run_name(cfg.sitl)
    out = out_dir(args, Path("out") / "eval" / f"{name}-dpose")
    run = run_dpose(cfg, sim.scenario(cfg), DPOSE_ARM_S)
    table = write_dpose(run, out, f"d-Pose on {name}")
    ms = np.array(run.dpose_ms)
    print(table)
    print(
        f"d-Pose cost per frame: median {np.median(ms):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms"
    )
    print(f"tables and plot in {out}")
    return EXIT_OK


def _dpose_random(cfg: Config, n: int) -> int:
    """d-Pose over n random synthetic poses above the marks painted from 3 m, without and with
    two distractor dots."""
    from companion.reporting import format_random_study

    pattern = armed_pattern(np.stack([r.spec().T_body_rf for r in cfg.rangefinders]))
    for distractors in (0, 2):
        st = random_pose_study(
            cfg.camera.model(),
            cfg.camera.T_body_cam(),
            pattern,
            n,
            seed=cfg.sitl.seed,
            distractors=distractors,
        )
        print(format_random_study(n, distractors, st, study_bands(st)))
    return EXIT_OK
