"""The parts in work as dispatch sees them, worked out again only when something changed.

H's view of the work for :meth:`cellctl.cell.controller.CellController._dispatch`: every part
waiting, active or held, as the scheduler's :class:`~cellctl.cell.scheduler.PartState`, the
places a held part may occupy, and the parts waiting at a mill to be cut there. All of it
follows from the journal and the mailbox alone, so it is kept until either changes
(:meth:`OrderFlow.version <cellctl.cell.orderflow.OrderFlow.version>`); and the robot's next
transfer is kept as long as that and the cell's inputs to the scheduler stay the same::

    view = controller.workview  # WorkView(world=..., alarms=..., orderflow=...)
    work = view.current()
    transfer = view.next_transfer(work, mills_in_service=..., pallet_present=..., ...)
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from cellctl.cell.config import CONVEYOR, transfer_ends
from cellctl.cell.orderflow import OUT
from cellctl.cell.scheduler import PartState, Transfer, next_transfer, ready_to_leave

if TYPE_CHECKING:
    from cellctl.cell.journal import Journal, Part
    from cellctl.cell.orderflow import OrderFlow
    from cellctl.cell.ports import AlarmSink, WorldModel


@dataclass(frozen=True)
class Work:
    """The parts in work at one version of the journal and the mailbox."""

    #: Each part waiting, active or held, in creation order, as the scheduler sees it.
    states: tuple[PartState, ...]
    #: Those parts as the journal has them.
    parts: tuple[Part, ...]
    #: Places a held part may physically occupy (after an interrupted transfer, both ends).
    blocked: frozenset[str]
    #: ``(part id, mill)``: a part waiting at a mill where its route cuts it next.
    to_machine: tuple[tuple[str, str], ...]
    #: Whether a part waits on the conveyor (a pallet is worth asking for).
    waiting_on_conveyor: bool


class WorkView:
    """The controller's view of the work (see module docstring)."""

    def __init__(self, world: WorldModel, alarms: AlarmSink, orderflow: OrderFlow) -> None:
        self.world = world
        self.log = alarms.log
        self.orderflow = orderflow
        self._work: tuple[Hashable, Work] | None = None
        self._planned: tuple[Hashable, Transfer | None] | None = None

    def current(self) -> Work:
        """The work now: worked out again only once the journal or the mailbox changed."""
        version = self.orderflow.version()
        if version is not None and self._work is not None and self._work[0] == version:
            return self._work[1]
        work = self._work_out()
        # The version from before: a step this found accepted (a write) makes the next call
        # look again, and find the same.
        self._work = (version, work)
        return work

    def next_transfer(
        self,
        work: Work,
        *,
        mills_in_service: set[str],
        pallet_present: bool,
        outfeed_clear: bool,
        policy: str,
        work_s: Mapping[str, float] | None,
    ) -> Transfer | None:
        """:func:`cellctl.cell.scheduler.next_transfer` for ``work``: the same answer as long
        as the work and these inputs stay the same, so it is worked out again only then."""
        version = self._work[0] if self._work is not None and self._work[1] is work else None
        basis = (version, frozenset(mills_in_service), pallet_present, outfeed_clear, policy)
        if version is not None and self._planned is not None and self._planned[0] == basis:
            return self._planned[1]
        transfer = next_transfer(
            work.states,
            self.world.config.parts,
            mills_in_service=mills_in_service,
            pallet_present=pallet_present,
            outfeed_clear=outfeed_clear,
            policy=policy,
            work_s=work_s,
        )
        self._planned = (basis, transfer)
        return transfer

    def _work_out(self) -> Work:
        world = self.world
        types = world.config.parts
        orders = {o.id: o for o in world.mailbox.orders()}
        parts = world.journal.parts(statuses=["waiting", "active", "held"])
        states = []
        for p in parts:
            order = orders.get(p.order_id)
            route_index = p.route_index
            route = types[p.part_type].route
            # A step the operator accepted after an interruption counts as done. The journal
            # says so at once: every later step (and the next transfer) starts from the
            # advanced index, also once the part has left this mill.
            if (
                p.status == "waiting"
                and route_index < len(route)
                and p.location == route[route_index].mill
                and world.journal.step_done(
                    p.id, "machine", p.location, route[route_index].name, route_index
                )
            ):
                route_index += 1
                world.journal.move_part(p.id, p.location, route_index)
                self.log(f"part {p.id}: {route[route_index - 1].name} accepted by the operator")
            states.append(
                PartState(
                    p.id,
                    p.part_type,
                    p.location,
                    route_index,
                    p.status,
                    priority=order.priority if order else 0,
                    order_seq=int(order.created * 1e6) if order else 0,
                )
            )
        to_machine = []
        for ps in states:
            if ps.status != "waiting" or ps.location == CONVEYOR or ready_to_leave(ps, types):
                continue
            # Not where its route says: the operator decides (never cut here).
            if types[ps.part_type].route[ps.route_index].mill == ps.location:
                to_machine.append((ps.id, ps.location))
        return Work(
            states=tuple(states),
            parts=tuple(parts),
            blocked=frozenset(self._blocked(parts)),
            to_machine=tuple(to_machine),
            waiting_on_conveyor=any(
                s.location == CONVEYOR and s.status == "waiting" for s in states
            ),
        )

    def _blocked(self, parts: list[Part]) -> set[str]:
        return held_places(self.world.journal, parts)


def held_places(journal: Journal, parts: Iterable[Part]) -> set[str]:
    """The places the held ones of ``parts`` may be in (:func:`places_of`): no part goes
    there until the operator says where each is."""
    return {where for p in parts if p.status == "held" for where in places_of(journal, p)}


def places_of(journal: Journal, part: Part) -> set[str]:
    """The machines ``part`` may physically be in: where the journal has it, and the target
    of a transfer it was in when interrupted (the arm may have put it down there); never the
    conveyor or the outfeed."""
    places = {part.location}
    steps = journal.steps(part.id)
    if steps and steps[-1].kind == "transfer" and steps[-1].state != "finished":
        places.add(transfer_ends(steps[-1].program)[1])
    return places - {CONVEYOR, OUT}
