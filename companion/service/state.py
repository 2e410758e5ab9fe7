"""State that must survive a restart of the service: the last ``reset_counter`` sent.

EKF2 (and EKF3) reset their external-vision states when ``reset_counter`` changes; a position
jump with the same counter is fused as a real motion or rejected by the innovation gate. The
pipeline counts VO re-initialisations from 0 in every process, so a crash and a restart (systemd
restarts us) would send a new origin under the last counter if the counter were only the
pipeline's. The service therefore sends ``(base + pipeline counter) mod 256``, where ``base``
is one more than the last value sent by any earlier run, read from the state folder; every
new value is persisted (atomically) before the first pose that carries it goes out.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from companion.bounded import read_regular_file
from companion.drivers.files import atomic_write
from companion.errors import ConfigError

log = logging.getLogger("companion.service")

RESET_COUNTER_FILE = "reset_counter"


def state_dir(configured: str) -> Path:
    """service.state_dir, or the default: $STATE_DIRECTORY (systemd's StateDirectory=), else
    $XDG_STATE_HOME/companion, else ~/.local/state/companion."""
    if configured:
        return Path(configured)
    if os.environ.get("STATE_DIRECTORY"):
        return Path(os.environ["STATE_DIRECTORY"].split(":")[0])
    if os.environ.get("XDG_STATE_HOME"):
        return Path(os.environ["XDG_STATE_HOME"]) / "companion"
    return Path.home() / ".local" / "state" / "companion"


class ResetCounter:
    """Maps the pipeline's reset counter to the one on the wire, never repeating the last value
    an earlier run sent (uint8: it wraps after 256 changes, as the field does)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.write_errors = 0
        last = self._read()
        if last is None:  # unreadable: any value but a fixed one is unlikely to repeat it
            self.base = int(time.time()) % 256
        else:  # -1 when no run sent anything yet: start at 0
            self.base = (last + 1) % 256
        self._written: int | None = None

    def _read(self) -> int | None:
        if not self.path.exists() and not self.path.is_symlink():
            return -1
        try:  # a regular file only, opened without blocking (a FIFO planted there: refused)
            text = read_regular_file(self.path, 64).decode("ascii").strip()
        except (ConfigError, UnicodeDecodeError) as e:
            log.warning("reset counter state %s unreadable (%s): base from the clock", self.path, e)
            return None
        if not text.isdigit() or int(text) > 255:
            log.warning(
                "reset counter state %s holds %r: base from the clock", self.path, text[:20]
            )
            return None
        return int(text)

    def wire(self, pipeline_counter: int) -> int:
        """The counter to send for the pipeline's ``pipeline_counter``; a new value is written
        to the state file before it is returned (a failed write is logged once, counted, and
        the value still sent: a stopped output would be worse)."""
        value = (self.base + pipeline_counter) % 256
        if value != self._written:
            try:
                atomic_write(self.path, f"{value}\n".encode(), 0o640)
            except OSError as e:
                if not self.write_errors:
                    log.warning("reset counter not persisted (%s): %s", self.path, e)
                self.write_errors += 1
            self._written = value
        return value
