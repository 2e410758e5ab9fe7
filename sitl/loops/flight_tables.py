"""What the missions' tables share (gps_table.py, loop_table.py): a number's cell, the rows of
flight folders sorted and joined under a header, and the command line ``OUT...``."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

Row = tuple[tuple[str, str, int], str]  # (autopilot, mission, seed), the markdown row


def fmt(v: Any, digits: int = 3) -> str:
    """A number with ``digits`` decimals; None: "-"."""
    return "-" if v is None else f"{float(v):.{digits}f}"


def render(header: str, row: Callable[[Path], Row], outs: list[Path]) -> str:
    """The markdown table: ``header``, its separator, one ``row`` per folder in key order."""
    rows = sorted(row(o) for o in outs)
    sep = "|" + "---|" * header.count(" |")
    return "\n".join([header, sep, *(r for _, r in rows)]) + "\n"


def main(module: str, table: Callable[[list[Path]], str], argv: list[str] | None) -> int:
    """``python -m MODULE OUT...``: the table on stdout; no folder: usage, exit 2."""
    args = sys.argv[1:] if argv is None else argv
    if not args:
        print(f"usage: python -m {module} OUT...", file=sys.stderr)
        return 2
    sys.stdout.write(table([Path(a) for a in args]))
    return 0
