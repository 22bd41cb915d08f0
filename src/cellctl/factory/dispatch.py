"""Which cell gets an order: pure functions of what the cells said and where orders went.

::

    cell, why = choose(order, store.cells(), store.orders(OPEN_STATES))
    # cell: the online cell that makes the part type with the earliest estimated finish;
    # None and why ("no online cell makes wax-robot-base") when none can take it now.

A cell's estimated finish is its own ``finish_estimate_s`` (its scheduler's bottleneck bound
of the parts it holds, from its retained state), plus what the orders the factory gave it
since that state add (``qty`` x the part type's ``bound_s``), plus the order itself.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

from cellctl.factory.store import AT_CELL_STATES, SENT, CellSeen, FactoryOrder


def load_s(cell: CellSeen, orders: Iterable[FactoryOrder]) -> float:
    """Seconds of work ``cell`` has: its own estimate, plus orders it got since it said so."""
    base = float(cell.state.get("finish_estimate_s") or 0.0)
    since = cell.state_time or 0.0
    bounds = cell.part_types
    pending = 0.0
    for o in orders:
        if o.cell != cell.name:
            continue
        # Sent and not yet answered, or accepted after the state: not in its estimate yet.
        if o.state == SENT or (o.state in AT_CELL_STATES and (o.accepted or 0.0) > since):
            pending += o.qty * bounds.get(o.part_type, 0.0)
    return base + pending


def choose(
    order: FactoryOrder, cells: Mapping[str, CellSeen], open_orders: Sequence[FactoryOrder]
) -> tuple[str | None, str]:
    """The cell to send ``order`` to, or None and why none can take it now."""
    makers = [c for c in cells.values() if order.part_type in c.part_types]
    if not makers:
        return None, f"no cell makes {order.part_type}"
    fresh = [c for c in makers if c.name not in order.refused]
    if not fresh:
        return None, f"refused by every cell that makes {order.part_type}"
    online = [c for c in fresh if c.status == "online"]
    if not online:
        return None, f"waiting for a cell that makes {order.part_type} to come online"
    # A paused cell takes orders but starts nothing: only when no other can.
    running = [c for c in online if not c.state.get("paused")] or online

    def finish(c: CellSeen) -> tuple[float, int, int, str]:
        total = load_s(c, open_orders) + order.qty * c.part_types[order.part_type]
        # Ties (cells alike, none measured yet): fewer parts of this type, then fewer parts,
        # as the factory itself knows them (a cell's own count lags a burst of orders).
        mine = [o for o in open_orders if o.cell == c.name]
        alike = sum(o.qty for o in mine if o.part_type == order.part_type)
        return (round(total, 6), alike, sum(o.qty for o in mine), c.name)

    best = min(running, key=finish)
    return best.name, ""


def every_cell_refused(order: FactoryOrder, cells: Iterable[str]) -> bool:
    """Whether each of the factory's cells has refused ``order``."""
    return set(cells) <= set(order.refused)
