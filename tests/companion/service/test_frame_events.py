"""The GPS frame's STATUSTEXT events (companion/service/frame_events.py): a few words per
transition, each within one STATUSTEXT with the prefix, nothing while [gps] align is off."""

from __future__ import annotations

import pytest

from companion.service import frame_events
from companion.service.statustext import INITIAL, MAX_TEXT_CHARS, OperatorState, Severity


def state(frame: str | None, agree: float | None = None, gap: float | None = None) -> OperatorState:
    return OperatorState(frame=frame, frame_agree_m=agree, frame_to_target_m=gap)


@pytest.mark.parametrize(
    ("before", "after", "severity", "text"),
    [
        ("own", "aligning", Severity.INFO, "GPS good, aligning frame"),
        ("aligning", "aligned", Severity.INFO, "frame aligned to GPS, agree 0.12 m"),
        ("aligning", "slewing", Severity.INFO, "GPS frame found, slewing 0.9 m"),
        ("aligned", "held", Severity.WARNING, "GPS lost, frame held"),
        ("held", "slewing", Severity.NOTICE, "GPS back, slewing 0.9 m"),
        ("slewing", "aligned", Severity.INFO, "frame aligned to GPS, agree 0.12 m"),
        ("aligning", "own", Severity.NOTICE, "GPS lost before alignment"),
    ],
)
def test_each_transition_says_itself_in_a_few_words(
    before: str, after: str, severity: Severity, text: str
) -> None:
    (event,) = frame_events.transitions(state(before, 0.5), state(after, 0.1234, 0.94))
    assert (event.key, event.severity, event.text) == ("frame", severity, text)
    assert len(event.text) <= MAX_TEXT_CHARS


def test_nothing_without_a_change_or_with_the_option_off() -> None:
    assert frame_events.transitions(state("aligned", 0.1), state("aligned", 0.3)) == []
    assert frame_events.transitions(INITIAL, state(None)) == []
    assert frame_events.transitions(INITIAL, state("own")) == []  # the first snapshot
    assert frame_events.transitions(state("held"), state("held")) == []


def test_unknown_figures_are_left_out() -> None:
    (event,) = frame_events.transitions(state("held"), state("slewing"))
    assert event.text == "GPS back, slewing"
    (event,) = frame_events.transitions(state("slewing"), state("aligned"))
    assert event.text == "frame aligned to GPS"
