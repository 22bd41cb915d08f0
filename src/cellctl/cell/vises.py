"""Vises emptied by hand: opened by the robot before their mill takes a part again.

A part scrapped out of a mill (``cellctl part scrap ID --taken-out``) leaves the mill's vise as
the arm left it, closed: only the robot's output opens it, and the loads wait for "vise open"
before they go in (their guard against a blank put onto a part still clamped). The journal
keeps each place the operator said is empty (:meth:`~cellctl.cell.journal.Journal.
emptied_places`); dispatch asks :meth:`EmptiedVises.look` what to do with them::

    look = controller.vises.look(work, inputs)
    look.to_open    # the mill whose vise the robot opens now (its ``open_vise_<mill>``)
    look.waiting    # the mills that take no part until their vise is open

Only a place vouched for by the operator is opened: a closed vise the journal has no word
of (a part the cell never knew of, left in a mill) is left to the load's own guard. A place
is no longer emptied once its vise shows open, or once a part is there again (released
there). Without the program, or after it failed (an alarm on the mill, code ``vise``), the
mill waits for its vise, opened by hand, or for the alarm to be cleared and the program tried
again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from cellctl.cell.config import open_vise_name
from cellctl.cell.workview import held_places

if TYPE_CHECKING:
    from collections.abc import Mapping

    from cellctl.cell.ports import AlarmSink, WorldModel
    from cellctl.cell.workview import Work

#: The alarm code of a vise that stays closed on an emptied mill.
VISE = "vise"


@dataclass(frozen=True)
class ViseLook:
    """What dispatch does about the emptied vises now (see module docstring)."""

    to_open: str | None = None
    waiting: frozenset[str] = field(default_factory=frozenset)


class EmptiedVises:
    """The controller's emptied vises (see module docstring)."""

    def __init__(self, world: WorldModel, alarms: AlarmSink) -> None:
        self.world = world
        self.alarms = alarms

    def look(self, work: Work, inputs: Mapping[str, bool]) -> ViseLook:
        """The emptied mills at the PLC's ``inputs`` and the parts in ``work``."""
        world = self.world
        emptied = world.journal.emptied_places()
        if not emptied:
            return ViseLook()
        mills = {m.name for m in world.config.mills}
        waiting: set[str] = set()
        for place, part_id in emptied.items():
            is_mill = place in mills
            closed = is_mill and inputs.get(f"clamp_closed_{world.mill_index(place)}", False)
            # The part taken out is no part there again: ``work`` may be from before the
            # operator's word (a scrap that landed while dispatch looked) and still show it.
            others = [p for p in work.parts if p.id != part_id]
            occupied = {p.location for p in others} | held_places(world.journal, others)
            if not closed or place in occupied:
                # Open (by the robot, or by hand), a part there again, or no mill: done.
                world.journal.vise_open(place)
                if is_mill and not closed:
                    self.alarms.returned(place, VISE)
                    self.alarms.log(f"{place}: its vise is open, it takes parts again")
                continue
            waiting.add(place)
            if open_vise_name(place) not in world.config.robot_programs:
                self.alarms.alarm(
                    place,
                    VISE,
                    f"{place}'s vise is closed with nothing in it (part {part_id} was taken "
                    f"out): open it by hand, or give the cell a robot program "
                    f"{open_vise_name(place)}; {place} takes no part until it is open",
                )
        to_open = next(
            (
                m
                for m in sorted(waiting)
                if open_vise_name(m) in world.config.robot_programs and not self._alarmed(m)
            ),
            None,
        )
        return ViseLook(to_open, frozenset(waiting))

    def _alarmed(self, mill: str) -> bool:
        """An alarm on ``mill``'s vise is not cleared: its program is not run again."""
        return self.world.journal.open_alarm(mill, VISE) is not None
