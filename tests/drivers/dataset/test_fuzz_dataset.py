"""A seeded fuzz of the dataset reader and of `companion eval` (the issue "Reliability round 3"):
2,000 damaged datasets (random byte flips, truncations, hostile CSV fields and rows, TOML
values and nesting, images of the wrong size or with a bomb's header, missing and empty files,
FIFOs and links out of the folder), made from a small recording of ours and a EuRoC folder.
Each must end in a clean refusal (DatasetError, one line; exit 2) or a completed read or eval
(exit 0): no traceback, no hang, the process's peak memory under a bound."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
CASES = 2000
SEED = 45
EVAL_EVERY = 20  # 100 of the 2,000 through `companion eval`, the rest through the reader
CASE_LIMIT_S = 20.0  # a case past this is a hang (they take milliseconds)
PEAK_RSS_MB = 600.0  # the whole fuzz process: Python, NumPy, OpenCV, the pipeline and a case
FUZZ_LIMIT_S = 600.0  # the whole fuzz (about a minute on the 2-core machine, unloaded)

RUN = textwrap.dedent(
    """
    import json, sys, tempfile
    from pathlib import Path
    sys.path.insert(0, "tests")
    from peers.hostile_datasets import fuzz
    with tempfile.TemporaryDirectory() as tmp:
        tally = fuzz(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), Path(tmp),
                     float(sys.argv[4]))
    print(json.dumps(tally))
    """
)


def test_2000_damaged_datasets_end_cleanly_without_hang_or_memory_blowup() -> None:
    args = [str(v) for v in (CASES, SEED, EVAL_EVERY, CASE_LIMIT_S)]
    r = subprocess.run(
        [sys.executable, "-c", RUN, *args],
        capture_output=True,
        text=True,
        timeout=FUZZ_LIMIT_S + 120,
        cwd=REPO,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    tally = json.loads(r.stdout.strip().splitlines()[-1])
    print(
        f"fuzz: {tally['cases']} datasets in {tally['seconds']:.1f} s ({tally['read']} read, "
        f"{tally['refused']} refused, evals by exit code {tally['evals']}), slowest case "
        f"{tally['slowest_s']:.2f} s, peak RSS {tally['peak_rss_mb']:.0f} MB"
    )
    assert tally["tracebacks"] == [], tally["tracebacks"][:3]
    assert tally["hangs"] == [] and tally["multiline"] == [], tally
    assert tally["cases"] == CASES and sum(tally["evals"].values()) == CASES // EVAL_EVERY
    assert set(tally["evals"]) <= {"0", "2"}
    assert tally["peak_rss_mb"] < PEAK_RSS_MB
    assert tally["seconds"] < FUZZ_LIMIT_S
