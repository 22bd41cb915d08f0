"""A running cell's state now, as a plan's inputs: what ``plan.run`` plays forward on a copy.

::

    orders, held = open_work(mailbox, journal)   # orders not finished, parts held now
    out = sorted(journal.machines_out_of_service())

Each order not finished (posted, accepted, in progress, held) is played with what remains
of it: its quantity less the parts done, scrapped, cancelled and held. A held part stays held
where it is (:class:`~cellctl.plan.engine.HeldPart`): the plan does not guess the operator's
word on it. A part on its way is taken up where it is (``PlanOrder.under_way``): at a mill
with the cuts it has, the plan goes on with it as the controller would after a restart. A
cut in flight now is taken up as far as it has gone (``PartAt.done_s``: the time since its
step began, in machine seconds); a transfer in flight is played again whole (seconds).
"""

from __future__ import annotations

from cellctl.cell.config import CONVEYOR
from cellctl.cell.journal import Journal
from cellctl.mailbox import Mailbox
from cellctl.plan.engine import HeldPart, PartAt, PlanOrder

#: Order states still to be worked on.
OPEN_STATES = ("posted", "accepted", "in-progress", "held")


def open_work(
    mailbox: Mailbox, journal: Journal | None, *, now: float | None = None, time_scale: float = 1.0
) -> tuple[tuple[PlanOrder, ...], tuple[HeldPart, ...]]:
    """The orders still to make (their remaining quantities) and the parts held now.

    ``now``: the cell's clock now (default: the journal's), what a cut in flight has done is
    counted to; ``time_scale``: the cell's (``[cell] time_scale``: an emulated cell's
    machines run that many times faster than the plan's)."""
    orders: list[PlanOrder] = []
    held: list[HeldPart] = []
    cutting: dict[str, float] = {}  # part id -> when its cut in flight began
    if journal is not None:
        cutting = {s.part_id: s.started for s in journal.open_steps() if s.kind == "machine"}
        now = journal.clock.now() if now is None else now
    for order in mailbox.orders(states=list(OPEN_STATES)):
        parts = journal.parts(order_id=order.id) if journal is not None else []
        settled = sum(p.status in ("done", "scrapped", "cancelled", "held") for p in parts)
        for p in parts:
            if p.status == "held":
                held.append(HeldPart(order.id, p.part_type, p.location, p.route_index))
        under_way = tuple(
            PartAt(p.location, p.route_index, _done(cutting.get(p.id), now, time_scale))
            for p in parts
            if p.status in ("waiting", "active") and (p.location != CONVEYOR or p.route_index)
        )
        remaining = order.qty - settled
        if remaining > 0:
            orders.append(
                PlanOrder(order.id, order.part_type, remaining, order.priority, under_way=under_way)
            )
    return tuple(orders), tuple(held)


def _done(since: float | None, now: float | None, time_scale: float) -> float:
    """Machine seconds of a cut begun at ``since`` done by ``now`` (0: none in flight)."""
    if since is None or now is None:
        return 0.0
    return round(max(0.0, now - since) * time_scale, 3)


def out_of_service(journal: Journal | None) -> tuple[str, ...]:
    """The machines out of automatic service now (the journal's record of it)."""
    return tuple(sorted(journal.machines_out_of_service())) if journal is not None else ()
