"""An open alarm's ISA-18.2 state in a few capital words, as every board shows it::

    alarm_marks(acked=None, returned=1.7e9, shelved_until=None, now=now)   # "UNACKED RTN"

UNACKED or acked; RTN once its condition has returned to normal (it stays open until
cleared); SHELVED while shelved.
"""

from __future__ import annotations


def alarm_marks(
    *, acked: float | None, returned: float | None, shelved_until: float | None, now: float
) -> str:
    """The marks of an open alarm with these fields (the API's ``alarms.list``) at ``now``."""
    marks = ["UNACKED" if acked is None else "acked"]
    if returned is not None:
        marks.append("RTN")
    if (shelved_until or 0) > now:
        marks.append("SHELVED")
    return " ".join(marks)
