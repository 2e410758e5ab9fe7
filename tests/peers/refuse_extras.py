"""The extras' modules a board never installs, and the import finder that refuses them.

``REFUSE_EXTRAS`` is Python source for a probe run in a fresh interpreter: with a name
``BLOCKED`` (module names) defined before it, it refuses every import of those modules and
their submodules, records each attempt in ``attempts`` and raises ModuleNotFoundError, so a
probe shows what the board's code would try to import (tests/e2e/test_packaging.py,
tests/e2e/test_check_arm64.py).
"""

from __future__ import annotations

# what only the simulator (sim extra), the evaluation (eval extra) or their dependencies bring
EXTRAS_ONLY = (
    "numba",
    "llvmlite",
    "skimage",
    "matplotlib",
    "evo",
    "pandas",
    "tomli_w",
    "filterpy",  # dev only since issue 39: its import pulled scipy.stats into the service
    "companion.sitl",
)

REFUSE_EXTRAS = r"""
import importlib.abc, sys

attempts = []


class RefuseExtras(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if any(name == b or name.startswith(b + ".") for b in BLOCKED):
            attempts.append(name)
            raise ModuleNotFoundError(f"blocked by the test: {name}", name=name)
        return None


sys.meta_path.insert(0, RefuseExtras())
"""
