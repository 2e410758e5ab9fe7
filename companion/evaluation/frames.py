"""The frames of a run that never reached the VO, counted by reason and said in one line.

Reasons (keys, in the order they are shown): the frame check's verdicts
(``companion.vo.frame_check.FrameProblem`` values: ``frozen`` = a repeated image, i.e. a
duplicated frame, ``out_of_order``, ``dark``, ``saturated``, ``blank``), ``held_for_attitude``
(the VO had not started and no autopilot attitude was at hand: ``Pipeline.held_for_attitude``),
``held_by_service`` (a flight recording's frames the service held from its VO), ``errors``
(frames the pipeline raised on in a replay, skipped as the service skips them).
"""

from __future__ import annotations

from collections.abc import Mapping

LABELS = {
    "frozen": "frozen (duplicated)",
    "out_of_order": "out of order",
    "dark": "dark",
    "saturated": "saturated",
    "blank": "blank",
    "held_for_attitude": "held for the autopilot's attitude",
    "held_by_service": "held from the VO by the service",
    "errors": "the pipeline raised",
}


def dropped_total(counts: Mapping[str, int]) -> int:
    """Frames not given to the VO, over every reason."""
    return sum(counts.values())


def dropped_line(frames: int, counts: Mapping[str, int]) -> str | None:
    """``"eval: 37 of 723 frames not given to the VO: 35 frozen (duplicated), 2 out of
    order"`` for ``frames`` frames in the dataset and the counts by reason (None when no frame
    was dropped). Reasons with no frame are left out; unknown reasons are shown by key."""
    total = dropped_total(counts)
    if total == 0:
        return None
    order = [k for k in LABELS if counts.get(k, 0)] + sorted(
        k for k, v in counts.items() if v and k not in LABELS
    )
    parts = [f"{counts[k]} {LABELS.get(k, k)}" for k in order]
    return f"eval: {total} of {frames} frames not given to the VO: " + ", ".join(parts)
