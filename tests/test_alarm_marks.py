"""An open alarm's ISA-18.2 marks, one wording on every board (the console's alarm lines,
`cellctl run`'s live view)."""

from __future__ import annotations

from cellctl.ui.alarm_marks import alarm_marks
from cellctl.ui.console.cellmenu import alarm_line

NOW = 1_800_000_000.0


def test_each_state_of_an_open_alarm_is_marked() -> None:
    assert alarm_marks(acked=None, returned=None, shelved_until=None, now=NOW) == "UNACKED"
    assert alarm_marks(acked=NOW - 5, returned=None, shelved_until=None, now=NOW) == "acked"
    # Its condition gone, still open until cleared: RTN, not a fault now.
    assert alarm_marks(acked=None, returned=NOW - 1, shelved_until=None, now=NOW) == "UNACKED RTN"
    assert (
        alarm_marks(acked=NOW - 9, returned=NOW - 1, shelved_until=NOW + 60, now=NOW)
        == "acked RTN SHELVED"
    )
    # A shelve whose time ran out is no shelve.
    assert alarm_marks(acked=None, returned=None, shelved_until=NOW - 1, now=NOW) == "UNACKED"


def test_the_consoles_alarm_line_says_the_same_marks() -> None:
    alarm = {
        "machine": "vf2",
        "code": "status",
        "text": "alarm 086 DR OFF",
        "priority": "high",
        "acked": None,
        "returned": NOW - 1,
        "shelved_until": None,
    }
    assert alarm_line(alarm, NOW) == "vf2 status: alarm 086 DR OFF [high UNACKED RTN]"
