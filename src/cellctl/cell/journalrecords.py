"""What the journal records: parts, steps, alarms and their active spells, and what a
recovery did.

Kept apart from :mod:`cellctl.cell.journal` so that its in-memory views
(:mod:`cellctl.cell.journalview`) can hold them without importing the journal; import them
from :mod:`cellctl.cell.journal` as before.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple


@dataclass(frozen=True)
class Part:
    """One workpiece. ``route_index`` counts the route operations the controller completed;
    ``note`` says why a part is held or scrapped."""

    id: str
    order_id: str
    part_type: str
    seq_in_order: int
    route_index: int
    location: str
    status: str
    updated: float
    note: str = ""


@dataclass(frozen=True)
class Step:
    """One step on one part; ``route_index`` is the part's route index when it began.

    ``attempt`` counts steps with the same part, kind, machine, program and route index.
    ``resolution`` is the operator's word on an interrupted or failed step: ``accepted``
    (counts as done) or ``redo`` (run it again).
    """

    id: int
    part_id: str
    kind: str
    machine: str
    program: str
    state: str
    started: float
    ended: float | None
    outcome: str
    attempt: int
    route_index: int = 0
    resolution: str = ""


@dataclass(frozen=True)
class Alarm:
    """An alarm after ISA-18.2: ``state`` is ``active`` until the operator clears it
    (``cleared`` time, ``cleared_by``), which ends it.

    Apart from that: ``acked`` is when the operator acknowledged it (None: unacknowledged),
    ``returned`` when its condition was last seen to go away (returned to normal; None: still
    seen, or not a condition the monitor watches; each time it was active, before and after
    a return, is one of its :class:`Spell`), ``shelved_until`` until when it is shelved
    (hidden from the unacknowledged list; back once that time is past).
    ``priority`` comes from its code (:data:`cellctl.cell.causes.ALARM_PRIORITY`).
    """

    id: int
    raised: float
    machine: str
    code: str
    text: str
    state: str
    cleared: float | None
    cleared_by: str = ""
    priority: str = "medium"
    acked: float | None = None
    acked_by: str = ""
    returned: float | None = None
    shelved_until: float | None = None
    shelved_by: str = ""

    def shelved(self, now: float) -> bool:
        """True while the alarm is shelved at ``now``."""
        return self.shelved_until is not None and self.shelved_until > now

    def unacked(self, now: float) -> bool:
        """True if the alarm is open, unacknowledged and not shelved at ``now``: what a
        control room shows flashing."""
        return self.state == "active" and self.acked is None and not self.shelved(now)


class Spell(NamedTuple):
    """One time an alarm was active: from ``began`` (raised, or its condition back after it
    returned to normal) to ``ended`` (returned to normal, else cleared; None: active still)."""

    began: float
    ended: float | None


@dataclass(frozen=True)
class RecoveryReport:
    """What :meth:`Journal.recover` did: steps it marked interrupted, parts it held.

    Each held part's ``note`` says why; post a ``part-held`` report and an alarm for each.
    """

    interrupted: list[Step] = field(default_factory=list)
    held: list[Part] = field(default_factory=list)

    @property
    def clean(self) -> bool:
        """True when nothing was in flight: the last run ended cleanly."""
        return not self.interrupted
