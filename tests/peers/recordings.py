"""Small flight recordings for tests, made as the service's recorder makes them: a seeded SITL
flight (``companion.sitl.world.dataset.record``) fed through a fresh ``Pipeline`` in the
service's order (per frame its attitudes, its ranges, then the frame, checked by the intake),
each frame and its samples written by ``DatasetWriter`` with every pose the pipeline gave
(``published.csv``), and the flight's ground truth kept (``groundtruth.txt``)."""

from __future__ import annotations

import shutil
from pathlib import Path

from companion.config import load_config
from companion.drivers.dataset import DatasetWriter, dataset_steps, open_dataset
from companion.pipeline import Pipeline
from peers import small_camera


def simulated_flight(out: Path, seconds: float = 5.0, seed: int = 3) -> Path:
    """A seeded figure eight over the town, 320x240, recorded as a dataset into ``out``."""
    from companion.sitl.world.dataset import record

    overrides = small_camera()
    overrides["sitl"] = {
        "terrain": "urban",
        "trajectory": "figure8",
        "seconds": seconds,
        "seed": seed,
    }
    record(load_config(overrides=overrides), out, progress=False)
    return out


def service_recording(flight: Path, out: Path, software: str = "companion test") -> Path:
    """``flight`` (a dataset) as the flight recorder would have written it in ``out``: the
    frames that pass the frame check with the samples fed before each, in the service's
    order, and the poses the pipeline gave as ``published.csv``; its ground truth copied."""
    ds = open_dataset(flight)
    assert ds.config is not None
    pipe = Pipeline(ds.config, ds.camera, ds.T_body_cam)
    writer = DatasetWriter(out, ds.config, software=software)
    for step in dataset_steps(ds):
        ranges = [r.sample for r in step.ranges if r.sample is not None]
        for sample in (*step.attitudes, *ranges):
            pipe.feed(sample)
        if pipe.check_frame(step.frame) is not None:
            continue  # refused by the intake: neither recorded nor fed (its samples are)
        writer.write_frame(step.frame, writer.encode(step.frame.image_bgr), ranges, step.attitudes)
        pose = pipe.feed_frame(step.frame, checked=True)
        if pose is not None:
            writer.write_pose(pose)
        pipe.background_work()
    writer.close()
    shutil.copy(flight / "groundtruth.txt", out / "groundtruth.txt")
    return out
