"""The factory's own state: ``<factory>/state/factory.db`` (SQLite, 0600, every call one
committed transaction, so a factory killed with -9 and started again loses nothing).

::

    store = FactoryStore(config.state_path)
    store.submit("wax-robot-base", 2, priority=0)          # queued
    store.submit("wax-robot-base", 2, due=resolve_due("FRI 18:00", now))  # due then
    store.send(order_id, "cell1", now, expires)            # sent: before the publish
    store.take_report("cell1", report)                     # accepted, done ... (idempotent)
    store.cancel(order_id, by="ann", reason="wrong stock") # cancelled, or asked of its cell
    store.orders(); store.cells(); store.events()

An order is ``queued`` (at no cell), ``sent`` (to one cell, not yet answered), then as its
cell reports it: ``accepted``, ``in-progress``, ``held`` (a part waits for the cell's
operator), and at last ``done``, ``failed`` or ``cancelled``. A refusal, or a cell that went
offline without taking it before its deadline, puts it back to ``queued`` with that cell
remembered, so it goes elsewhere. An order's ``due`` time (unix seconds, or none) is kept as
submitted and goes to its cell with it.

A cancel (:mod:`cellctl.factory.cancel`) ends a queued order at once. For an order at a cell
it is a request kept beside the state (``cancel_asked``, ``cancel_by``, ``cancel_reason``):
the order is shown ``cancelling`` (:attr:`FactoryOrder.shown_state`) while its state goes on
following the cell's reports, until the cell's ``order-cancelled`` ends it or its
``cancel-refused`` withdraws the request.

A cell's reports are taken in order, per mailbox: the next ``seq`` of the epoch the factory
follows. A report of a new epoch (the cell's mailbox was made anew) starts that epoch; one
past a gap, or from the middle of a new epoch, is refused, and :meth:`take_report` says which
seq to ask the cell for again.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from cellctl.cell.sqlitedb import SqliteStore
from cellctl.clock import Clock, current_clock
from cellctl.errors import UsageError
from cellctl.factory.following import apply_report
from cellctl.factory.records import (
    ACCEPTED,
    ANSWER_KINDS,
    AT_CELL_STATES,
    CANCEL_COLUMNS,
    CANCELLED,
    CANCELLING,
    DONE,
    FAILED,
    FINAL_STATES,
    HELD,
    IN_PROGRESS,
    OPEN_STATES,
    QUEUED,
    SENT,
    CellSeen,
    FactoryEvent,
    FactoryOrder,
    Taken,
    cell_of,
    log_event,
    order_of,
)
from cellctl.mailbox.base import MAX_QTY, check_due, check_new_order
from cellctl.mailbox.wire import MAX_NAME, MAX_REASON, ReportMessage
from cellctl.plan.when import when_text

__all__ = [
    "ACCEPTED",
    "AT_CELL_STATES",
    "CANCELLED",
    "CANCELLING",
    "DONE",
    "FAILED",
    "FINAL_STATES",
    "HELD",
    "IN_PROGRESS",
    "OPEN_STATES",
    "QUEUED",
    "SENT",
    "CellSeen",
    "FactoryEvent",
    "FactoryOrder",
    "FactoryStore",
    "Taken",
]

SCHEMA = """
CREATE TABLE IF NOT EXISTS orders (
    id TEXT PRIMARY KEY,
    part_type TEXT NOT NULL,
    qty INTEGER NOT NULL,
    priority INTEGER NOT NULL,
    state TEXT NOT NULL,
    cell TEXT,
    note TEXT NOT NULL DEFAULT '',
    submitted REAL NOT NULL,
    updated REAL NOT NULL,
    sent REAL,
    last_send REAL,
    sends INTEGER NOT NULL DEFAULT 0,
    expires REAL,
    accepted REAL,
    accepted_seen REAL,
    finished REAL,
    refused TEXT NOT NULL DEFAULT '[]',
    done INTEGER NOT NULL DEFAULT 0,
    held INTEGER NOT NULL DEFAULT 0,
    scrapped INTEGER NOT NULL DEFAULT 0,
    cancel_asked REAL,
    cancel_by TEXT,
    cancel_reason TEXT,
    cancel_sent REAL,
    cancel_sends INTEGER NOT NULL DEFAULT 0,
    held_parts TEXT NOT NULL DEFAULT '[]',
    due REAL
);
CREATE TABLE IF NOT EXISTS cells (
    name TEXT PRIMARY KEY,
    status TEXT NOT NULL DEFAULT 'unknown',
    status_time REAL,
    state TEXT,
    state_time REAL,
    seq INTEGER NOT NULL DEFAULT 0,
    epoch TEXT
);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    time REAL NOT NULL,
    cell TEXT,
    order_id TEXT,
    text TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS orders_by_state ON orders (state)
"""


#: What :meth:`FactoryStore.cancel` did: cancelled at once, asked of the order's cell, or
#: nothing (a cancel was on its way already).
Outcome = Literal["cancelled", "asked", "pending"]


class FactoryStore(SqliteStore):
    """The factory's SQLite file (see module docstring); ``clock`` gives the times recorded
    (its ``now()``; None: the running loop's clock, read when a time is recorded)."""

    def __init__(self, path: Path, *, clock: Clock | None = None) -> None:
        super().__init__(path, SCHEMA)
        self._clock = clock
        with self._write() as db:  # a store from before epochs
            columns = {row["name"] for row in db.execute("PRAGMA table_info(cells)")}
            if "epoch" not in columns:
                db.execute("ALTER TABLE cells ADD COLUMN epoch TEXT")
            columns = {row["name"] for row in db.execute("PRAGMA table_info(orders)")}
            for name, kind in CANCEL_COLUMNS.items():  # a store from before cancels
                if name not in columns:
                    db.execute(f"ALTER TABLE orders ADD COLUMN {name} {kind}")

    def _now(self) -> float:
        return (self._clock or current_clock()).now()

    # -- orders in ----------------------------------------------------------------------------

    def submit(
        self,
        part_type: str,
        qty: int,
        priority: int = 0,
        order_id: str | None = None,
        *,
        due: float | None = None,
    ) -> tuple[FactoryOrder, bool]:
        """Queue an order, due at ``due`` (unix seconds; None: no due time); the same id again
        returns the first one unchanged (new=False)."""
        oid = check_new_order(part_type, qty, priority, order_id)
        due = check_due(due)
        if len(oid) > MAX_NAME or len(part_type) > MAX_NAME:
            raise UsageError(f"an order id and a part type have at most {MAX_NAME} characters")
        if qty > MAX_QTY:
            raise UsageError(f"order quantity must be at most {MAX_QTY}, not {qty}")
        now = self._now()
        with self._write() as db:
            row = db.execute("SELECT * FROM orders WHERE id = ?", (oid,)).fetchone()
            if row is not None:
                return order_of(row), False
            db.execute(
                "INSERT INTO orders (id, part_type, qty, priority, state, submitted, updated, due)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (oid, part_type, qty, priority, QUEUED, now, now, due),
            )
            shown = "" if due is None else f", due {when_text(due, date=True)}"
            log_event(db, now, None, oid, f"order {oid} submitted: {qty} x {part_type}{shown}")
            row = db.execute("SELECT * FROM orders WHERE id = ?", (oid,)).fetchone()
        return order_of(row), True

    def get(self, order_id: str) -> FactoryOrder:
        rows = self._read("SELECT * FROM orders WHERE id = ?", (order_id,))
        if not rows:
            raise UsageError(f"no order {order_id!r} in the factory")
        return order_of(rows[0])

    def orders(self, states: Sequence[str] | None = None) -> list[FactoryOrder]:
        """Orders, highest priority first, then oldest first."""
        sql = "SELECT * FROM orders"
        args: list[Any] = []
        if states:
            sql += f" WHERE state IN ({','.join('?' * len(states))})"
            args = list(states)
        sql += " ORDER BY priority DESC, submitted, id"
        return [order_of(r) for r in self._read(sql, args)]

    # -- dispatch -----------------------------------------------------------------------------

    def send(self, order_id: str, cell: str, expires: float) -> FactoryOrder:
        """Give a queued order to ``cell``: committed before the order goes out."""
        return self.send_many([(order_id, cell)], expires)[0]

    def send_many(
        self,
        choices: Sequence[tuple[str, str]],
        expires: float,
        reasons: Mapping[str, str] | None = None,
    ) -> list[FactoryOrder]:
        """Give each queued order of ``choices`` (order id, cell) to its cell, in one commit;
        ``reasons`` (by order id) are logged in that commit too: no order is seen sent
        without why."""
        now = self._now()
        out = []
        with self._write() as db:
            for order_id, cell in choices:
                row = db.execute("SELECT * FROM orders WHERE id = ?", (order_id,)).fetchone()
                if row is None:
                    raise UsageError(f"no order {order_id!r} in the factory")
                order = order_of(row)
                if order.state in FINAL_STATES:
                    continue  # cancelled from the command line since it was chosen
                if order.state != QUEUED:
                    raise UsageError(f"order {order_id} is {order.state}, not queued")
                db.execute(
                    "UPDATE orders SET state = ?, cell = ?, sent = COALESCE(sent, ?),"
                    " last_send = ?, sends = sends + 1, expires = ?, updated = ?, note = ?"
                    " WHERE id = ?",
                    (SENT, cell, now, now, expires, now, f"sent to {cell}", order_id),
                )
                # Why first: a reader sees the choice, then the order going.
                if reasons and order_id in reasons:
                    log_event(db, now, cell, order_id, f"order {order_id}: {reasons[order_id]}")
                log_event(db, now, cell, order_id, f"order {order_id} sent to {cell}")
                row = db.execute("SELECT * FROM orders WHERE id = ?", (order_id,)).fetchone()
                out.append(order_of(row))
        return out

    def resent(self, order_id: str) -> None:
        """Count one more send of an order still waiting for its cell's answer."""
        with self._write() as db:
            db.execute(
                "UPDATE orders SET last_send = ?, sends = sends + 1 WHERE id = ? AND state = ?",
                (self._now(), order_id, SENT),
            )

    def requeue(self, order_id: str, cell: str, why: str) -> None:
        """The order is not at ``cell`` (refused, or never taken): queue it for another."""
        now = self._now()
        with self._write() as db:
            row = db.execute("SELECT * FROM orders WHERE id = ?", (order_id,)).fetchone()
            if row is None:
                return
            order = order_of(row)
            if order.state != SENT or order.cell != cell or order.cancelling:
                return  # a late or repeated answer, or one to cancel: it stays where it is
            refused = [*order.refused, cell] if cell not in order.refused else list(order.refused)
            db.execute(
                "UPDATE orders SET state = ?, cell = NULL, expires = NULL, refused = ?,"
                " updated = ?, note = ? WHERE id = ?",
                (QUEUED, json.dumps(refused), now, f"{cell}: {why}", order_id),
            )
            log_event(db, now, cell, order_id, f"order {order_id} back from {cell}: {why}")

    def fail(self, order_id: str, why: str) -> None:
        """No cell can make it: the order fails with ``why``."""
        now = self._now()
        with self._write() as db:
            db.execute(
                "UPDATE orders SET state = ?, note = ?, updated = ?, finished = ? WHERE id = ?"
                " AND state = ?",
                (FAILED, why, now, now, order_id, QUEUED),
            )
            log_event(db, now, None, order_id, f"order {order_id} failed: {why}")

    def note(self, order_id: str, text: str) -> bool:
        """Say why a queued order waits (shown by `cellctl factory orders`); True when the
        note changed."""
        with self._write() as db:
            cur = db.execute(
                "UPDATE orders SET note = ? WHERE id = ? AND note != ? AND state = ?",
                (text, order_id, text, QUEUED),
            )
            return cur.rowcount > 0

    # -- cancels ------------------------------------------------------------------------------

    def cancel(self, order_id: str, *, by: str, reason: str = "") -> tuple[FactoryOrder, Outcome]:
        """Cancel an order for ``by`` (who asks) and ``reason``, and say how it went:
        ``cancelled`` (it was queued: at once), ``asked`` (its cell is to cancel it) or
        ``pending`` (a cancel is on its way already: nothing changes). UsageError for an
        unknown order or one that has ended."""
        if len(reason) > MAX_REASON:
            raise UsageError(f"a reason has at most {MAX_REASON} characters, not {len(reason)}")
        if not 1 <= len(by) <= MAX_NAME:
            raise UsageError(f"who cancels is named in 1 to {MAX_NAME} characters")
        now = self._now()
        why = f"by {by}" + (f": {reason}" if reason else "")
        with self._write() as db:
            row = db.execute("SELECT * FROM orders WHERE id = ?", (order_id,)).fetchone()
            if row is None:
                raise UsageError(f"no order {order_id!r} in the factory")
            order = order_of(row)
            if order.state in FINAL_STATES:
                raise UsageError(f"order {order_id} is {order.state}: there is nothing to cancel")
            if order.cancelling:
                return order, "pending"
            outcome: Outcome
            asked = "cancel_asked = ?, cancel_by = ?, cancel_reason = ?, cancel_sent = NULL"
            if order.state == QUEUED:
                db.execute(
                    f"UPDATE orders SET state = ?, finished = ?, note = ?, updated = ?, {asked}"
                    " WHERE id = ?",
                    (CANCELLED, now, f"cancelled {why}", now, now, by, reason, order_id),
                )
                log_event(db, now, None, order_id, f"order {order_id} cancelled {why} (at no cell)")
                outcome = "cancelled"
            else:
                note = f"cancelling at {order.cell}: asked {why}"
                db.execute(
                    f"UPDATE orders SET note = ?, updated = ?, {asked} WHERE id = ?",
                    (note, now, now, by, reason, order_id),
                )
                text = f"order {order_id}: cancel asked {why}; {order.cell} is to cancel it"
                log_event(db, now, order.cell, order_id, text)
                outcome = "asked"
            row = db.execute("SELECT * FROM orders WHERE id = ?", (order_id,)).fetchone()
        return order_of(row), outcome

    def cancelling(self) -> list[FactoryOrder]:
        """Orders whose cancel is on its way to their cell, oldest request first."""
        rows = self._read(
            f"SELECT * FROM orders WHERE cancel_asked IS NOT NULL AND state IN"
            f" ({','.join('?' * len(OPEN_STATES))}) ORDER BY cancel_asked, id",
            OPEN_STATES,
        )
        return [order_of(r) for r in rows]

    def cancel_sent(self, order_id: str) -> None:
        """Count one more send of an order's cancel to its cell (the first one logged)."""
        now = self._now()
        with self._write() as db:
            row = db.execute("SELECT * FROM orders WHERE id = ?", (order_id,)).fetchone()
            if row is None or not order_of(row).cancelling:
                return
            db.execute(
                "UPDATE orders SET cancel_sent = ?, cancel_sends = cancel_sends + 1 WHERE id = ?",
                (now, order_id),
            )
            if row["cancel_sent"] is None:
                log_event(
                    db,
                    now,
                    row["cell"],
                    order_id,
                    f"order {order_id}: cancel sent to {row['cell']}",
                )

    def cancel_here(self, order_id: str, why: str) -> bool:
        """Cancel a sent order its cell can no longer take (gone past its ``expires``) in the
        store; True when it was."""
        now = self._now()
        with self._write() as db:
            cur = db.execute(
                "UPDATE orders SET state = ?, finished = ?, note = ?, updated = ? WHERE id = ?"
                " AND state = ? AND cancel_asked IS NOT NULL",
                (CANCELLED, now, f"cancelled: {why}", now, order_id, SENT),
            )
            if cur.rowcount:
                log_event(db, now, None, order_id, f"order {order_id} cancelled: {why}")
            return cur.rowcount > 0

    # -- what cells say -----------------------------------------------------------------------

    def cells(self) -> dict[str, CellSeen]:
        return {r["name"]: cell_of(r) for r in self._read("SELECT * FROM cells ORDER BY name")}

    def set_status(self, cell: str, status: str) -> bool:
        """Record a cell's online/offline; True when it changed."""
        now = self._now()
        with self._write() as db:
            row = db.execute("SELECT status FROM cells WHERE name = ?", (cell,)).fetchone()
            if row is not None and row["status"] == status:
                return False
            db.execute(
                "INSERT INTO cells (name, status, status_time) VALUES (?, ?, ?) ON CONFLICT(name)"
                " DO UPDATE SET status = excluded.status, status_time = excluded.status_time",
                (cell, status, now),
            )
            log_event(db, now, cell, None, f"{cell} {status}")
            return True

    def set_state(self, cell: str, state: dict[str, Any]) -> None:
        with self._write() as db:
            db.execute(
                "INSERT INTO cells (name, state, state_time) VALUES (?, ?, ?) ON CONFLICT(name)"
                " DO UPDATE SET state = excluded.state, state_time = excluded.state_time",
                (cell, json.dumps(state), float(state.get("time", self._now()))),
            )

    def take_report(self, cell: str, report: ReportMessage) -> Taken:
        """Follow an order through one of ``cell``'s reports (see the module docstring).

        Reports come at least once: one at or below the last seen seq changes nothing, except
        an answer (accepted, rejected) sent again for a re-sent order.
        """
        now = self._now()
        with self._write() as db:
            row = db.execute("SELECT seq, epoch FROM cells WHERE name = ?", (cell,)).fetchone()
            last, epoch = (row["seq"], row["epoch"]) if row is not None else (0, None)
            if report.epoch != epoch:
                # The cell's mailbox was made anew (or this is the first report heard):
                # follow the new one from its start.
                last = 0
                db.execute(
                    "INSERT INTO cells (name, seq, epoch) VALUES (?, 0, ?) ON CONFLICT(name)"
                    " DO UPDATE SET seq = 0, epoch = excluded.epoch",
                    (cell, report.epoch),
                )
                log_event(
                    db, now, cell, None, f"{cell}: reports of mailbox {report.epoch} from now"
                )
            if report.seq > last + 1:
                why = f"report {report.seq} refused: the next one is {last + 1}"
                return Taken(ask_after=last, refused=why)
            if report.seq <= last and report.kind not in ANSWER_KINDS:
                return Taken()
            if report.seq == last + 1:
                db.execute("UPDATE cells SET seq = ? WHERE name = ?", (report.seq, cell))
            oid = report.order_id
            if oid is None or report.withdrawn:
                return Taken()
            found = db.execute("SELECT * FROM orders WHERE id = ?", (oid,)).fetchone()
            if found is None:
                return Taken()  # an order the cell had from elsewhere (its own mailbox)
            text = apply_report(db, order_of(found), cell, report, now)
            if text:
                log_event(db, now, cell, oid, text)
            return Taken(text)

    def data_version(self) -> int:
        """Changes when another process commits (an order submitted from the CLI)."""
        return int(self._read("PRAGMA data_version")[0][0])

    # -- the log ------------------------------------------------------------------------------

    def log(self, text: str, cell: str | None = None, order_id: str | None = None) -> None:
        with self._write() as db:
            log_event(db, self._now(), cell, order_id, text)

    def events(self, after: int = 0, limit: int = 200) -> list[FactoryEvent]:
        rows = self._read(
            "SELECT * FROM events WHERE id > ? ORDER BY id DESC LIMIT ?", (after, limit)
        )
        return [FactoryEvent(**dict(r)) for r in reversed(rows)]
