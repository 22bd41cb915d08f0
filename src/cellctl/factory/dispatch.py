"""Which cell gets an order: pure functions of what the cells said and where orders went.

::

    cell, why = choose(order, store.cells(), store.orders(OPEN_STATES), Estimating("plan", now))
    # cell: the online cell that makes the part type, with every machine its route needs in
    # service, with the earliest estimated finish, and why it: "cell2 by its plan: 412 s";
    # None and why none can take it now ("waiting for a cell that can make wax-robot-base
    # now (cell1 has cnc2 out of service; cell2 is offline)").

A cell's estimated finish is what it holds now, plus what the orders the factory gave it
since it said so add (``qty`` x the part type's ``bound_s``), plus the order itself. What it
holds now is, by default, its own ``finish_estimate_s`` (its scheduler's bottleneck bound of
the parts it holds, from its retained state). With ``[dispatch] estimate = "plan"`` it is its
plan's finish instead (``plan_finish_s`` after ``planned_at``: the cell played its own state
forward on virtual time), less the time gone since, when the plan is at most ``plan_age``
seconds old; a cell without a fresh plan is counted by its bound.

Every figure is in the cell's own seconds (its clock's, whether it measured the part type or
not: an emulated cell divides the machines' seconds by its ``[cell] time_scale`` before it
publishes them, :mod:`cellctl.cell.estimate`), so they add up and cells compare fairly.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Final, Literal

from cellctl.factory.store import AT_CELL_STATES, SENT, CellSeen, FactoryOrder

#: What a cell's work now is counted by (``[dispatch] estimate`` in factory.toml).
BOUND: Final = "bound"
PLAN: Final = "plan"
ESTIMATES: Final = (BOUND, PLAN)
EstimateKind = Literal["bound", "plan"]
#: Seconds a cell's plan stays fresh by default (``[dispatch] plan_age``).
PLAN_AGE_S: Final = 600.0
#: Seconds a plan may seem to come from the future (the hosts' clocks a little out of step).
SKEW_S: Final = 5.0


@dataclass(frozen=True)
class Estimating:
    """How a cell's finish is estimated: by its bound, or by its plan when one is fresh.

    ``now``: the factory's time (unix seconds) the plans' ages are taken at; ``plan_age``:
    seconds after ``planned_at`` that a plan still counts.
    """

    estimate: EstimateKind = BOUND
    now: float = 0.0
    plan_age: float = PLAN_AGE_S


def _pending_s(cell: CellSeen, orders: Iterable[FactoryOrder], since: float) -> float:
    """Seconds the orders the factory gave ``cell`` after ``since`` add (by their bounds)."""
    bounds = cell.part_types
    pending = 0.0
    for o in orders:
        if o.cell != cell.name:
            continue
        # Sent and not yet answered, or accepted after ``since``: not in its estimate yet.
        if o.state == SENT or (o.state in AT_CELL_STATES and (o.accepted or 0.0) > since):
            pending += o.qty * bounds.get(o.part_type, 0.0)
    return pending


def load_s(cell: CellSeen, orders: Iterable[FactoryOrder]) -> float:
    """Seconds of work ``cell`` has by its bound: its own estimate, plus orders it got since
    it said so."""
    base = float(cell.state.get("finish_estimate_s") or 0.0)
    return base + _pending_s(cell, orders, cell.state_time or 0.0)


def plan_load_s(
    cell: CellSeen, orders: Iterable[FactoryOrder], now: float, age: float
) -> float | None:
    """Seconds of work ``cell`` has from ``now`` by its plan, plus orders it got since it
    planned; None when it has no plan at most ``age`` seconds old (or one from the future:
    a clock far out of step)."""
    finish = cell.state.get("plan_finish_s")
    planned = cell.state.get("planned_at")
    if not isinstance(finish, int | float) or not isinstance(planned, int | float):
        return None
    if not -SKEW_S <= now - planned <= age:
        return None
    left = max(0.0, float(planned) + float(finish) - now)
    return left + _pending_s(cell, orders, float(planned))


def estimate_s(
    cell: CellSeen, orders: Iterable[FactoryOrder], how: Estimating
) -> tuple[float, EstimateKind]:
    """Seconds of work ``cell`` has now, and what counted it (``plan`` or ``bound``)."""
    orders = list(orders)
    if how.estimate == PLAN:
        planned = plan_load_s(cell, orders, how.now, how.plan_age)
        if planned is not None:
            return planned, PLAN
    return load_s(cell, orders), BOUND


def candidates(order: FactoryOrder, cells: Mapping[str, CellSeen]) -> tuple[list[CellSeen], str]:
    """The cells ``order`` may go to now, or none and why: online, making its part type, with
    every machine a part of it needs in service (its state's ``part_types[*].machines`` and
    ``machines[*].in_service``), and not paused unless only paused ones can."""
    makers = [c for c in cells.values() if order.part_type in c.part_types]
    if not makers:
        return [], f"no cell makes {order.part_type}"
    fresh = [c for c in makers if c.name not in order.refused]
    if not fresh:
        return [], f"refused by every cell that makes {order.part_type}"
    online = [c for c in fresh if c.status == "online"]
    if not online:
        return [], f"waiting for a cell that makes {order.part_type} to come online"
    # A machine its route needs out of service: an order there would wait, stuck, however
    # low the cell's bound (an accepted order never moves).
    able = [c for c in online if not c.out_of_service(order.part_type)]
    if not able:
        return [], _unable(order.part_type, fresh)
    # A paused cell takes orders but starts nothing: only when no other can.
    return [c for c in able if not c.state.get("paused")] or able, ""


def _unable(part: str, cells: Iterable[CellSeen]) -> str:
    """Why none of ``cells`` (each makes ``part``) can take it now: each cell and why."""
    whys = []
    for c in cells:
        out = c.out_of_service(part) if c.status == "online" else []
        if c.status != "online":
            whys.append(f"{c.name} is offline")
        elif out:
            whys.append(f"{c.name} has {', '.join(out)} out of service")
    return f"waiting for a cell that can make {part} now ({'; '.join(whys)})"


def finish_s(
    order: FactoryOrder, cell: CellSeen, open_orders: Sequence[FactoryOrder], how: Estimating
) -> tuple[float, EstimateKind]:
    """When ``cell`` would finish ``order`` if it got it (seconds from now), and by what."""
    held, kind = estimate_s(cell, open_orders, how)
    return held + order.qty * cell.part_types[order.part_type], kind


def choose(
    order: FactoryOrder,
    cells: Mapping[str, CellSeen],
    open_orders: Sequence[FactoryOrder],
    how: Estimating = Estimating(),
) -> tuple[str | None, str]:
    """The cell to send ``order`` to and why (its estimated finish, and whether its plan or
    its bound gave it), or None and why none can take it now."""
    running, why = candidates(order, cells)
    if not running:
        return None, why
    finishes = {c.name: finish_s(order, c, open_orders, how) for c in running}

    def key(c: CellSeen) -> tuple[float, int, int, str]:
        # Ties (cells alike, none measured yet): fewer parts of this type, then fewer parts,
        # as the factory itself knows them (a cell's own count lags a burst of orders).
        mine = [o for o in open_orders if o.cell == c.name]
        alike = sum(o.qty for o in mine if o.part_type == order.part_type)
        return (round(finishes[c.name][0], 6), alike, sum(o.qty for o in mine), c.name)

    best = min(running, key=key)
    total, kind = finishes[best.name]
    return best.name, f"{best.name} finishes it earliest by its {kind}: {total:.0f} s"


def every_cell_refused(order: FactoryOrder, cells: Iterable[str]) -> bool:
    """Whether each of the factory's cells has refused ``order``."""
    return set(cells) <= set(order.refused)


def stuck(
    order: FactoryOrder, cells: Mapping[str, CellSeen], configured: Iterable[str]
) -> tuple[str, bool]:
    """Why no cell can take ``order`` now, in the operator's words, and whether that is for
    good: True once every cell of ``configured`` (factory.toml's) has said what it makes (its
    state) and none that makes the part type is left that has not refused it.

    A cell that makes it and is offline, or online with a machine its route needs out of
    service, keeps it waiting (it comes back), and so does a cell never heard (it may make
    it)::

        why, never = stuck(order, store.cells(), config.cells)
        # ("no cell makes gear (the cells make: wax-robot-base)", True)
    """
    part = order.part_type
    refused = set(order.refused)
    heard = {n: cells[n] for n in configured if n in cells and cells[n].state}
    unheard = [n for n in configured if n not in heard and n not in refused]
    makers = [n for n, c in heard.items() if part in c.part_types]
    waiting = [n for n in makers if n not in refused]
    if any(heard[n].status == "online" for n in waiting):
        # Online, but a machine its route needs is out of service: it comes back.
        return _unable(part, (heard[n] for n in waiting)), False
    if waiting:
        return f"waiting for a cell that makes {part} to come online ({', '.join(waiting)})", False
    if unheard:
        them = ", ".join(unheard)
        return f"no cell heard so far makes {part}: waiting for {them} to say what it makes", False
    if makers:
        return f"refused by every cell that makes {part} ({order.note})", True
    made = sorted({t for c in heard.values() for t in c.part_types})
    why = f"no cell makes {part} (the cells make: {', '.join(made) or 'nothing'})"
    return (why + f"; {order.note}" if refused and order.note else why), True
