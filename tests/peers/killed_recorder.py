"""A recorder in a process of its own that records noise frames at a camera's pace until it
is killed (the SIGKILL tests of tests/companion/service/test_recorder.py and
test_recorder_mcap.py): ``python -c KILLED_RECORDER DIR FORMAT``; it prints "recording" once
a few frames are queued."""

from __future__ import annotations

import textwrap

KILLED_RECORDER = textwrap.dedent(
    """
    import sys, time, numpy as np
    sys.modules["tomli_w"] = None  # the service's install has no TOML writer (the sim extra)
    from companion.config import load_config
    from companion.service.recorder import Recorder
    from companion.types import AttitudeSample, CameraFrame, ImuSample, RangeSample
    camera = {"width": 320, "height": 240}  # the frames' size below
    record = {"dir": sys.argv[1], "format": sys.argv[2]}
    cfg = load_config(overrides={"record": record, "camera": camera})
    rec = Recorder(cfg.record, cfg).running()
    rng = np.random.default_rng(1)
    k = 0
    while True:  # until killed
        t = 1_000_000 + k * 33_333
        img = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
        rec.frame(
            CameraFrame(t, k, img),
            [RangeSample(t - 100, 1, 3.0 + k * 1e-3, 0.1, 40.0, 100)],
            [AttitudeSample(t - 50, np.array([1.0, 0, 0, 0]), np.zeros(3))],
        )
        if k == 5:
            print("recording", flush=True)
        k += 1
        time.sleep(0.01)  # a camera's pace: the recorder keeps up
    """
)
