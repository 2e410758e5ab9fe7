"""The GPS frame's transitions as STATUSTEXT events ([gps] align; pure, as statustext.py).

The frame's state, agreement and distance to its target are fields of
:class:`companion.service.statustext.OperatorState` (``frame``, ``frame_agree_m``,
``frame_to_target_m``; the service fills them from ``gps_frame``); :func:`transitions` says
what changed between two snapshots in a few words, under the key ``frame`` (a newer state
replaces an unsent older one in the limiter).
"""

from __future__ import annotations

from companion.service.statustext import Event, OperatorState, Severity


def transitions(prev: OperatorState, cur: OperatorState) -> list[Event]:
    """The GPS frame's transitions: aligned (INFO, with the agreement), held (WARNING),
    slewing after a return or onto a first alignment (NOTICE / INFO, with the distance), back
    to our own frame before any alignment (NOTICE)."""
    if cur.frame == prev.frame or cur.frame is None or prev.frame is None:
        return []
    if cur.frame == "aligned":
        agree = f", agree {cur.frame_agree_m:.2f} m" if cur.frame_agree_m is not None else ""
        return [Event("frame", Severity.INFO, f"frame aligned to GPS{agree}")]
    if cur.frame == "held":
        return [Event("frame", Severity.WARNING, "GPS lost, frame held")]
    if cur.frame == "slewing":
        gap = f" {cur.frame_to_target_m:.1f} m" if cur.frame_to_target_m is not None else ""
        back = prev.frame == "held"
        text = f"GPS back, slewing{gap}" if back else f"GPS frame found, slewing{gap}"
        return [Event("frame", Severity.NOTICE if back else Severity.INFO, text)]
    if cur.frame == "own":
        return [Event("frame", Severity.NOTICE, "GPS lost before alignment")]
    return [Event("frame", Severity.INFO, "GPS good, aligning frame")]
