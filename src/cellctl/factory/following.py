"""One cell report's effect on the factory's order: its state and its counts, as the cell
reports them (:class:`~cellctl.mailbox.wire.ReportKind`). Called by
:meth:`~cellctl.factory.store.FactoryStore.take_report` inside its transaction, once per
report (the store takes each report of a mailbox once, in order)::

    text = apply_report(db, order, "cell1", report, now)   # what changed, in words, or None

- **held**: the parts of the order held for the cell's operator now, by id: a ``part-held``
  adds one, its ``part-released`` or ``part-scrapped`` takes it away (a waiting part
  scrapped was never held: nothing changes). The order is ``held`` while one is, else
  ``in-progress`` once anything of it has started.
- **done**: its parts made so far: a report with ``"part_done": true`` in its data (the
  ``step-finished`` that brings a part out, the ``part-released`` of a part released on the
  outfeed) counts one; ``order-done`` sets it to what the order made (its qty less its
  parts scrapped).
- **scrapped**: a ``part-scrapped`` counts one.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable
from typing import Any

from cellctl.factory.records import (
    ACCEPTED,
    AT_CELL_STATES,
    CANCELLED,
    ENDS,
    HELD,
    IN_PROGRESS,
    QUEUED,
    SENT,
    FactoryOrder,
)
from cellctl.mailbox.wire import ReportKind, ReportMessage

#: Reports that change which of an order's parts are held.
HOLDS = (ReportKind.PART_HELD, ReportKind.PART_RELEASED, ReportKind.PART_SCRAPPED)


def apply_report(
    db: sqlite3.Connection,
    order: FactoryOrder,
    cell: str,
    report: ReportMessage,
    now: float,
) -> str | None:
    """One report's effect on the order (one transaction with the seq it came with)."""
    oid = order.id
    kind = report.kind
    words = report.text

    def update(sql: str, *args: Any) -> None:
        db.execute(f"UPDATE orders SET {sql}, updated = ? WHERE id = ?", (*args, now, oid))

    if order.cell != cell:
        if kind == ReportKind.ORDER_ACCEPTED:
            # What the accept deadline exists to prevent: said loudly, nothing changed.
            where = order.cell or "the queue"
            return f"order {oid} accepted by {cell} too, after it went to {where}"
        return None
    if kind == ReportKind.CANCEL_REFUSED:
        return _cancel_refused(order, cell, report, update)
    if kind == ReportKind.ORDER_REJECTED and order.state == SENT and order.cancelling:
        # Refused, so never made there: that is the cancel done.
        note = f"cancelled: {cell} refused it ({words})"
        update("state = ?, finished = ?, note = ?", CANCELLED, now, note)
        return f"order {oid} cancelled: {cell} refused it: {words}"
    if kind == ReportKind.ORDER_ACCEPTED and order.state == SENT:
        t = report.time or now
        update("state = ?, accepted = ?, accepted_seen = ?, note = ?", ACCEPTED, t, now, words)
        return f"order {oid} accepted by {cell}"
    if kind == ReportKind.ORDER_REJECTED and order.state == SENT:
        # Refused for good, unless only too late: that cell may take it when sent again.
        late = report.data.get("expired") is True
        refused = list(order.refused) + ([] if late or cell in order.refused else [cell])
        update(
            "state = ?, cell = NULL, expires = NULL, refused = ?, note = ?",
            QUEUED,
            json.dumps(refused),
            f"{cell}: {words}",
        )
        return f"order {oid} refused by {cell}: {words}"
    if order.state not in (SENT, *AT_CELL_STATES):
        return None  # a report after the end, or one sent again
    if kind in ENDS:
        return _ended(order, cell, report, now, update)
    done = order.done + (1 if report.data.get("part_done") is True else 0)
    if kind == ReportKind.STEP_STARTED:
        state = HELD if order.held_parts else IN_PROGRESS
        update("state = ?, done = ?", state, done)
        return None
    if kind in HOLDS:
        return _holds(order, cell, report, done, update)
    if done != order.done:
        update("done = ?", done)
    return None


def _holds(
    order: FactoryOrder, cell: str, report: ReportMessage, done: int, update: Callable[..., None]
) -> str:
    """A part held, released or scrapped: the held parts, the state and the counts."""
    kind, part = report.kind, report.part_id
    held = [p for p in order.held_parts if p != part]
    if kind == ReportKind.PART_HELD:
        held.append(part or f"?{len(held) + 1}")  # a part id beyond the wire's: counted
    elif part is None and held and len(held) == len(order.held_parts):
        held.pop(0)  # no id (beyond the wire's limits): one of those without an id
    scrapped = order.scrapped + (1 if kind == ReportKind.PART_SCRAPPED else 0)
    # Held while a part waits for the operator; otherwise at work (something has started:
    # a part was held), or as it was (a waiting part scrapped before anything started).
    state = HELD if held else (IN_PROGRESS if order.state in (HELD, IN_PROGRESS) else order.state)
    update(
        "state = ?, held = ?, held_parts = ?, scrapped = ?, done = ?, note = ?",
        state,
        len(held),
        json.dumps(held),
        scrapped,
        done,
        report.text,
    )
    return f"{cell}: {report.text}"


def _ended(
    order: FactoryOrder,
    cell: str,
    report: ReportMessage,
    now: float,
    update: Callable[..., None],
) -> str:
    """The order done, failed or cancelled at its cell."""
    kind = report.kind
    state = ENDS[kind]
    done = order.qty - order.scrapped if kind == ReportKind.ORDER_DONE else order.done
    note = report.text
    if order.cancelling and kind == ReportKind.ORDER_CANCELLED:
        note += f" (asked by {order.cancel_by}" + (
            f": {order.cancel_reason})" if order.cancel_reason else ")"
        )
    elif order.cancelling:
        note += " (it ended before the cancel came)"
    update(
        "state = ?, finished = ?, done = ?, held = 0, held_parts = '[]', note = ?",
        state,
        now,
        done,
        note,
    )
    return f"order {order.id} {state} at {cell}: {note}"


def _cancel_refused(
    order: FactoryOrder, cell: str, report: ReportMessage, update: Callable[..., None]
) -> str | None:
    """The cell's own cancel refused the factory's: the order goes on there."""
    oid, words = order.id, report.text
    if order.state == CANCELLED and order.cancel_asked is not None:
        # Cancelled here once its cell stayed away past the deadline, and yet it has started
        # there (the one case the deadline cannot cover): said loudly.
        return f"order {oid} was cancelled here, but {cell} makes it: {words}"
    asked = report.data.get("asked")
    if not order.cancelling or (isinstance(asked, int | float) and asked != order.cancel_asked):
        return None  # an answer to an earlier request, or after the end
    update(
        "cancel_asked = NULL, cancel_sent = NULL, note = ?", f"{cell} did not cancel it: {words}"
    )
    return f"order {oid}: {cell} did not cancel it: {words}"
