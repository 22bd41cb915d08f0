"""A running cell's state now, as a plan's inputs: what ``plan.run`` plays forward on a copy.

::

    orders, held = open_work(mailbox, journal)   # orders not finished, parts held now
    out = sorted(journal.machines_out_of_service())

Each order not finished (posted, accepted, in progress, held) is played with what remains
of it: its quantity less the parts done, scrapped, cancelled and held. A held part stays held
where it is (:class:`~cellctl.plan.engine.HeldPart`): the plan does not guess the operator's
word on it. A part on its way is taken up where it is (``PlanOrder.under_way``): at a mill
with the cuts it has, the plan goes on with it as the controller would after a restart. A
step in flight now is played again whole (the journal records a step when it ends): the
plan errs late by at most that step's time.
"""

from __future__ import annotations

from cellctl.cell.config import CONVEYOR
from cellctl.cell.journal import Journal
from cellctl.mailbox import Mailbox
from cellctl.plan.engine import HeldPart, PartAt, PlanOrder

#: Order states still to be worked on.
OPEN_STATES = ("posted", "accepted", "in-progress", "held")


def open_work(
    mailbox: Mailbox, journal: Journal | None
) -> tuple[tuple[PlanOrder, ...], tuple[HeldPart, ...]]:
    """The orders still to make (their remaining quantities) and the parts held now."""
    orders: list[PlanOrder] = []
    held: list[HeldPart] = []
    for order in mailbox.orders(states=list(OPEN_STATES)):
        parts = journal.parts(order_id=order.id) if journal is not None else []
        settled = sum(p.status in ("done", "scrapped", "cancelled", "held") for p in parts)
        for p in parts:
            if p.status == "held":
                held.append(HeldPart(order.id, p.part_type, p.location, p.route_index))
        under_way = tuple(
            PartAt(p.location, p.route_index)
            for p in parts
            if p.status in ("waiting", "active") and (p.location != CONVEYOR or p.route_index)
        )
        remaining = order.qty - settled
        if remaining > 0:
            orders.append(
                PlanOrder(order.id, order.part_type, remaining, order.priority, under_way=under_way)
            )
    return tuple(orders), tuple(held)


def out_of_service(journal: Journal | None) -> tuple[str, ...]:
    """The machines out of automatic service now (the journal's record of it)."""
    return tuple(sorted(journal.machines_out_of_service())) if journal is not None else ()
