"""A flight recording made fast, without a flight: the committed real clip
(tests/data/real/tum_fr1_rpy_clip, colour 640 x 480 frames and synthesised distance sensors)
fed through a Pipeline as the service's worker feeds it (samples, the frame check, the
frame), with the Recorder taking each frame and each pose as the service hands them over."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from companion.drivers.dataset import dataset_steps, open_dataset
from companion.pipeline import Pipeline
from companion.service.recorder import Recorder
from companion.types import PoseEstimate

CLIP = Path(__file__).resolve().parents[1] / "data" / "real" / "tum_fr1_rpy_clip"


def record_clip(
    where: Path, frames: int = 60, **record: Any
) -> tuple[Recorder, list[PoseEstimate]]:
    """Record the clip's first ``frames`` usable frames into ``where`` ([record] options
    ``record`` over the defaults: an MCAP file ``where``.mcap unless ``format`` says else);
    returns the closed Recorder and the poses the pipeline made (all handed to it)."""
    ds = open_dataset(CLIP)
    assert ds.config is not None
    cfg = ds.config
    record.setdefault("queue_frames", frames + 60)  # a loaded machine's writer may lag
    options = dataclasses.replace(cfg.record, dir=str(where), **record)
    cfg = dataclasses.replace(cfg, record=options)
    pipe = Pipeline(cfg, ds.camera, ds.T_body_cam)
    poses: list[PoseEstimate] = []
    taken = 0
    with Recorder(cfg.record, cfg).running() as rec:
        for step in dataset_steps(ds):
            if taken >= frames:
                break
            ranges = [r.sample for r in step.ranges if r.sample is not None]
            for sample in [*step.attitudes, *ranges]:
                pipe.feed(sample)
            if pipe.check_frame(step.frame) is not None:
                continue
            rec.frame(step.frame, ranges, step.attitudes)
            pose = pipe.feed_frame(step.frame, checked=True)
            taken += 1
            if pose is not None:
                poses.append(pose)
                rec.pose(pose)
    return rec, poses
