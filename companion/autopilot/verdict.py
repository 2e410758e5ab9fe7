"""The verdict of a fusion diagnosis, PX4's (EKF2) or ArduPilot's (EKF3) (pure)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Verdict:
    """fused: True / False / None (cannot tell); reasons: most likely first (for None: why
    it cannot tell; for True: why the autopilot will not fly on it all the same, e.g. no heading
    alignment, GNSS fighting us); warnings: what is wrong but does not stop fusion;
    timesync_converged: PX4's time sync on our stamps (None: not seen)."""

    fused: bool | None
    headline: str
    reasons: tuple[str, ...]
    evidence: tuple[str, ...]
    warnings: tuple[str, ...]
    timesync_converged: bool | None = None

    @property
    def ok(self) -> bool:
        """Fused, with nothing that keeps the autopilot from flying on it."""
        return self.fused is True and not self.reasons
