"""The journal's in-memory views: what the controller reads every round, without SQLite.

:class:`~cellctl.cell.journal.Journal` keeps one :class:`JournalViews`, read whole from the
file on the first read and again whenever another connection committed (the CLI releasing a
part, an operator clearing an alarm); its own writes update it after they commit. Each
answer costs what the parts still in work, the alarms and the machines cost, not what the
journal's history holds: done parts stay in :attr:`JournalViews.parts` but no round looks
at them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Iterable

    from cellctl.cell.journalrecords import Alarm, Part, Step

#: What a step is known by for :meth:`JournalViews.step_done`.
StepKey = tuple[str, str, str, str, int]


class JournalViews:
    """Parts by status and by order, done steps, alarms, machines out of service and places
    emptied by hand."""

    def __init__(self) -> None:
        self.parts: dict[str, Part] = {}  # in creation (rowid) order
        self._rank: dict[str, int] = {}  # part id -> rowid
        self._by_status: dict[str, set[str]] = {}
        self._by_order: dict[str, list[str]] = {}
        self._done: set[StepKey] = set()
        self.alarms: dict[int, Alarm] = {}  # in id order
        self._active: set[int] = set()
        self._out: dict[str, str] = {}
        self._emptied: dict[str, str] = {}  # place -> the part taken out of it

    # -- updates ------------------------------------------------------------------------------

    def part(self, part: Part, rowid: int | None = None) -> bool:
        """A part as the file now has it (``rowid``: a new part's). False for a part these
        views never saw, without its rowid (another connection made it): read them again."""
        old = self.parts.get(part.id)
        if old is None:
            if rowid is None:
                return False
            self._rank[part.id] = rowid
            self._by_order.setdefault(part.order_id, []).append(part.id)
        elif old.status != part.status:
            self._by_status[old.status].discard(part.id)
        self.parts[part.id] = part
        self._by_status.setdefault(part.status, set()).add(part.id)
        return True

    def step(self, step: Step) -> None:
        """A step as the file now has it: one finished or accepted counts as done."""
        if step.state == "finished" or step.resolution == "accepted":
            self._done.add((step.part_id, step.kind, step.machine, step.program, step.route_index))

    def alarm(self, alarm: Alarm) -> None:
        """An alarm as the file now has it."""
        self.alarms[alarm.id] = alarm
        if alarm.state == "active":
            self._active.add(alarm.id)
        else:
            self._active.discard(alarm.id)

    def machine(self, name: str, in_service: bool, reason: str) -> None:
        """A machine's service as the file now has it."""
        if in_service:
            self._out.pop(name, None)
        else:
            self._out[name] = reason

    def emptied(self, place: str, part_id: str | None) -> None:
        """A place the operator emptied (``part_id`` taken out of it), or None: no more."""
        if part_id is None:
            self._emptied.pop(place, None)
        else:
            self._emptied[place] = part_id

    # -- answers ------------------------------------------------------------------------------

    def select_parts(self, statuses: Iterable[str] | None, order_id: str | None) -> list[Part]:
        """What ``SELECT * FROM parts WHERE ... ORDER BY rowid`` answers."""
        if order_id is not None:
            ids: Iterable[str] = self._by_order.get(order_id, ())
            if statuses is not None:
                wanted = set(statuses)
                return [p for p in map(self.parts.__getitem__, ids) if p.status in wanted]
            return [self.parts[i] for i in ids]
        if statuses is None:
            return list(self.parts.values())
        chosen: set[str] = set()
        for status in set(statuses):
            chosen |= self._by_status.get(status, set())
        return [self.parts[i] for i in sorted(chosen, key=self._rank.__getitem__)]

    def step_done(self, key: StepKey) -> bool:
        """Whether the step ``key`` finished or was accepted by the operator."""
        return key in self._done

    def active_alarms(self) -> list[Alarm]:
        """Alarms not cleared yet, oldest first."""
        return [self.alarms[i] for i in sorted(self._active)]

    def emptied_places(self) -> dict[str, str]:
        """``place -> part id`` for each place emptied by hand whose vise is not known open."""
        return dict(sorted(self._emptied.items()))

    def out_of_service(self) -> dict[str, str]:
        """``machine -> reason`` for each machine out of service, by name."""
        return dict(sorted(self._out.items()))
