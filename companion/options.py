"""The ``opt`` helper that every options dataclass uses (kept apart to avoid import cycles)."""

from __future__ import annotations

import dataclasses
from dataclasses import field
from typing import Any


def opt(default: Any, help: str, secret: bool = False, **bounds: float) -> Any:
    """A config field with a one-line help text, optional numeric bounds (ge, gt, le, lt), and
    ``secret`` for values that must never be logged (describe() prints them as ***)."""
    meta: dict[str, Any] = {"help": help, **bounds}
    if secret:
        meta["secret"] = True
    if isinstance(default, (list, dict, set)) or dataclasses.is_dataclass(default):
        value = default
        return field(default_factory=lambda: value, metadata=meta)
    return field(default=default, metadata=meta)
