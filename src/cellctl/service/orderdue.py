"""Orders' due times in the control API: ``orders.submit``'s ``due``, ``orders.list``'s ``due``
and ``late``::

    due = resolve_due("FRI 18:00", now)      # unix s: the next Friday 18:00 on the cell's clock
    resolve_due(1_796_400_000, now)           # unix seconds as they are; None: no due time
    submit_order(mailbox, ["wax-robot-base"], params)    # orders.submit (params.due resolved)
    list_orders(mailbox, journal)             # orders.list: each with "due" and "late"

``due`` is written as ``cellctl plan --until`` is (:func:`cellctl.plan.when.resolve_when`):
``FRI 18:00`` and ``18:00`` are the next such time, never one past; a date and time is itself
and may be past already: such an order is taken, and is late from the start (a planner
records the backlog as it is; the answer says so). An order is **late** once done after its
due time, or while not done (open, or failed) past it; a cancelled one is owed nothing.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from cellctl.cell.config import CellConfig
from cellctl.cell.journal import Journal
from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.mailbox import CANCELLED, DONE, Mailbox, Order
from cellctl.mailbox.base import check_due
from cellctl.plan.when import resolve_when, when_text
from cellctl.service import operator

if TYPE_CHECKING:
    from cellctl.service.params import SubmitParams

#: The longest due time read as text (``2026-12-04T18:00:00+01:00`` is 25 characters).
MAX_DUE_TEXT = 60


def resolve_due(given: object, now: float) -> float | None:
    """``given`` as a due time, unix seconds: None (no due time), unix seconds, or text as
    ``--until`` takes it, read at ``now`` (the cell's clock); UsageError in words otherwise."""
    if given is None:
        return None
    if isinstance(given, str):
        if len(given) > MAX_DUE_TEXT:
            raise UsageError(f"a due time is at most {MAX_DUE_TEXT} characters")
        return check_due(resolve_when(given, now, due=True))
    if isinstance(given, bool) or not isinstance(given, int | float):
        # Never its repr: a peer's list or object may be nested thousands deep.
        raise UsageError(f"a due time is unix seconds or text (FRI 18:00), not {_kind(given)}")
    return check_due(given)


def _kind(value: object) -> str:
    words = {bool: "true or false", list: "a list", dict: "an object"}
    return words.get(type(value), type(value).__name__)


def due_words(due: float | None, now: float) -> str:
    """What an order's message adds for its due time: ``, due Fri 2026-12-04 18:00:00``, with
    ``(already past: the order is late)`` for one before ``now``; "" for none."""
    if due is None:
        return ""
    past = " (already past: the order is late)" if due < now else ""
    return f", due {when_text(due, date=True)}{past}"


def _what(qty: int, part_type: str, priority: int, due: float | None) -> str:
    shown = "" if due is None else f", due {when_text(due, date=True)}"
    return f"{qty} × {part_type}, priority {priority}{shown}"


def submit_order(mailbox: Mailbox, part_types: list[str] | None, p: SubmitParams) -> dict[str, Any]:
    """``orders.submit``: post ``p``'s order, due at ``p.due`` (unix seconds: the params
    resolved it); ``part_types`` (from cell.toml) refuses unknown types when given. The same
    id again is the same order, or refused saying what the id stands for."""
    operator.check_part_type(part_types, p.part_type)
    now = current_clock().now()
    order, new = mailbox.post_order(p.part_type, p.qty, p.priority, p.id, due=p.due)
    due = mailbox.due_times().get(order.id)
    asked = (p.part_type, p.qty, p.priority, p.due)
    if new:
        what = _what(order.qty, order.part_type, order.priority, None)
        message = f"order {order.id} posted: {what}{due_words(due, now)}"
    elif (order.part_type, order.qty, order.priority, due) != asked:
        # The same id for another order: a retry must ask the same, or it is a mistake.
        raise UsageError(
            f"order {order.id} was posted before as "
            f"{_what(order.qty, order.part_type, order.priority, due)} ({order.state}), not "
            f"{_what(p.qty, p.part_type, p.priority, p.due)}: nothing changed (give this order "
            "another --id)"
        )
    else:
        message = f"order {order.id} was posted before ({order.state}): nothing changed"
    return {"order": order_entry(order, due, now), "new": new, "message": message}


def is_late(state: str, updated: float, due: float | None, now: float) -> bool:
    """Whether an order in ``state`` since ``updated`` is late at ``now``: done after its
    ``due`` time (it became done at ``updated``), or not done and past it; never without a
    due time, or cancelled."""
    if due is None or state == CANCELLED:
        return False
    if state == DONE:
        return updated > due
    return now > due


def order_entry(order: Order, due: float | None, now: float) -> dict[str, Any]:
    """An order as the API gives it: its record, ``due`` (unix s or None) and ``late``."""
    late = is_late(order.state, order.updated, due, now)
    return {**operator.as_dict(order), "due": due, "late": late}


def list_orders(
    mailbox: Mailbox,
    journal: Journal | None,
    states: list[str] | None = None,
    config: CellConfig | None = None,
) -> list[dict[str, Any]]:
    """``orders.list``: :func:`cellctl.service.operator.list_orders`, each order with its
    ``due`` time (unix s or None) and whether it is ``late`` now."""
    now = current_clock().now()
    found = operator.list_orders(mailbox, journal, states, config)
    # Read after the orders: an order posted between the two reads has its due time here.
    dues = mailbox.due_times()
    for entry in found:
        due = entry["due"] = dues.get(entry["id"])
        entry["late"] = is_late(entry["state"], entry["updated"], due, now)
    return found
