"""The SQLite mailbox: ``<cell_dir>/mailbox.sqlite3``, shared by the controller and the CLI.

Every call is one short transaction that is committed (and, with ``synchronous=FULL``,
on disk) before the call returns. Writers take the write lock up front (``BEGIN
IMMEDIATE``) so a read-modify-write cannot interleave with another process, and wait up to
``busy_timeout`` seconds for it rather than failing with "database is locked".

The orders are answered from memory, read again from the file only after another connection
(the CLI posting an order, say) committed: a controller asking every round costs no query.

An order's due time is its row's ``due`` (NULL: none). A file from before due times gains
the column when it is opened, its orders with none; a cellctl from before reads and writes
the file as it did (it names the columns it reads and writes).
"""

from __future__ import annotations

import json
import sqlite3
import uuid
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from cellctl.cell.sqlitedb import SqliteStore
from cellctl.clock import Clock, current_clock
from cellctl.errors import UsageError
from cellctl.mailbox.base import (
    POSTED,
    Mailbox,
    Order,
    Report,
    check_due,
    check_new_order,
    check_report_kind,
    check_transition,
)

SCHEMA = """
CREATE TABLE IF NOT EXISTS orders (
    id TEXT PRIMARY KEY,
    part_type TEXT NOT NULL,
    qty INTEGER NOT NULL,
    priority INTEGER NOT NULL,
    state TEXT NOT NULL,
    created REAL NOT NULL,
    updated REAL NOT NULL,
    note TEXT NOT NULL DEFAULT '',
    due REAL
);
CREATE TABLE IF NOT EXISTS reports (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    time REAL NOT NULL,
    kind TEXT NOT NULL,
    order_id TEXT,
    part_id TEXT,
    text TEXT NOT NULL,
    data TEXT NOT NULL DEFAULT '{}'
);
CREATE INDEX IF NOT EXISTS orders_by_state ON orders (state);
CREATE TABLE IF NOT EXISTS meta (
    key TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
"""


class SqliteMailbox(SqliteStore, Mailbox):
    """The default mailbox. ``SqliteMailbox(path)``; ``clock`` gives the times it records
    (its ``now()``; None: the running loop's clock, read when a time is recorded);
    ``durable=False`` only for a throwaway copy (see :func:`cellctl.cell.sqlitedb.connect`)."""

    def __init__(self, path: Path, *, clock: Clock | None = None, durable: bool = True) -> None:
        SqliteStore.__init__(self, path, SCHEMA, durable=durable)
        self._clock = clock
        with self._write() as db:
            # Made once, with the file (or on the first open of a file from before epochs).
            db.execute(
                "INSERT OR IGNORE INTO meta (key, value) VALUES ('epoch', ?)", (uuid.uuid4().hex,)
            )
            # A file from before due times: checked under the write lock, so two processes
            # opening it at once add the column once.
            if "due" not in {r["name"] for r in db.execute("PRAGMA table_info(orders)")}:
                db.execute("ALTER TABLE orders ADD COLUMN due REAL")
        self._epoch = str(self._read("SELECT value FROM meta WHERE key = 'epoch'")[0][0])
        # The orders by id, each with its sort key (highest priority first, then oldest;
        # rowid breaks ties between orders posted within the clock's resolution).
        self._orders: dict[str, tuple[tuple[int, float, int], Order]] = {}
        self._by_state: dict[str, set[str]] = {}
        self._dues: dict[str, float] = {}

    def _load_views(self, db: sqlite3.Connection) -> None:
        self._orders, self._by_state, self._dues = {}, {}, {}
        for row in db.execute("SELECT rowid AS rank, * FROM orders"):
            self._keep(_order(row), row["rank"], row["due"])

    def _keep(self, order: Order, rank: int | None = None, due: float | None = None) -> None:
        """Put ``order`` in the views: a new one with its ``rank`` and ``due`` (an order's
        due time never changes), a known one in its new state."""
        old = self._orders.get(order.id)
        if old is None:
            if rank is None:  # made by another connection: read everything again
                self._views_at = None
                return
            key = (-order.priority, order.created, rank)
            if due is not None:
                self._dues[order.id] = due
        else:
            key = old[0]
            self._by_state[old[1].state].discard(order.id)
        self._orders[order.id] = (key, order)
        self._by_state.setdefault(order.state, set()).add(order.id)

    @property
    def clock(self) -> Clock:
        """What the mailbox's times are read from: the clock given, else the running loop's."""
        return self._clock or current_clock()

    def _now(self) -> float:
        return self.clock.now()

    @property
    def epoch(self) -> str:
        return self._epoch

    def post_order(
        self,
        part_type: str,
        qty: int = 1,
        priority: int = 0,
        order_id: str | None = None,
        *,
        due: float | None = None,
    ) -> tuple[Order, bool]:
        oid = check_new_order(part_type, qty, priority, order_id)
        due = check_due(due)
        now = self._now()
        with self._write() as db:
            row = db.execute("SELECT * FROM orders WHERE id = ?", (oid,)).fetchone()
            if row is not None:
                return _order(row), False
            cur = db.execute(
                "INSERT INTO orders (id, part_type, qty, priority, state, created, updated, due)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (oid, part_type, qty, priority, POSTED, now, now, due),
            )
            order, rank = Order(oid, part_type, qty, priority, POSTED, now, now), cur.lastrowid
            self._after_commit(lambda: self._keep(order, rank, due))
        return order, True

    def due_times(self) -> dict[str, float]:
        with self._lock:
            self._views_current()
            return dict(self._dues)

    def get_order(self, order_id: str) -> Order:
        with self._lock:
            self._views_current()
            kept = self._orders.get(order_id)
        if kept is None:
            raise UsageError(f"no order {order_id!r}")
        return kept[1]

    def orders(self, states: Iterable[str] | None = None) -> list[Order]:
        with self._lock:
            self._views_current()
            if states is None:
                chosen = list(self._orders.values())
            else:
                ids: set[str] = set()
                for state in set(states):
                    ids |= self._by_state.get(state, set())
                chosen = [self._orders[i] for i in ids]
        return [order for _, order in sorted(chosen, key=lambda kept: kept[0])]

    def set_order_state(self, order_id: str, state: str, note: str = "") -> Order:
        with self._write() as db:
            row = db.execute("SELECT * FROM orders WHERE id = ?", (order_id,)).fetchone()
            if row is None:
                raise UsageError(f"no order {order_id!r}")
            order = _order(row)
            check_transition(order, state)
            if state == order.state and not note:
                return order
            now = self._now()
            # A new state says its own note (none: none); the same state keeps its note
            # unless given one (a held order's "a part needs the operator" is not the
            # in-progress order's once the part is released).
            new_note = note if note or state != order.state else order.note
            db.execute(
                "UPDATE orders SET state = ?, updated = ?, note = ? WHERE id = ?",
                (state, now, new_note, order_id),
            )
            changed = Order(
                order.id,
                order.part_type,
                order.qty,
                order.priority,
                state,
                order.created,
                now,
                new_note,
            )
            self._after_commit(lambda: self._keep(changed))
        return changed

    def post_report(
        self,
        kind: str,
        text: str,
        *,
        order_id: str | None = None,
        part_id: str | None = None,
        data: dict[str, Any] | None = None,
    ) -> Report:
        check_report_kind(kind)
        payload = dict(data or {})
        try:
            encoded = json.dumps(payload, sort_keys=True)
        except (TypeError, ValueError) as e:
            raise UsageError(f"report data must be JSON: {e}") from None
        now = self._now()
        with self._write() as db:
            cur = db.execute(
                "INSERT INTO reports (time, kind, order_id, part_id, text, data)"
                " VALUES (?, ?, ?, ?, ?, ?)",
                (now, kind, order_id, part_id, text, encoded),
            )
            seq = cur.lastrowid
        assert seq is not None
        return Report(seq, now, kind, order_id, part_id, text, payload)

    def reports(self, since_seq: int = 0, limit: int | None = None) -> list[Report]:
        sql = "SELECT * FROM reports WHERE seq > ? ORDER BY seq"
        args: list[int] = [since_seq]
        if limit is not None:
            sql += " LIMIT ?"
            args.append(limit)
        return [_report(r) for r in self._read(sql, args)]

    def close(self) -> None:
        SqliteStore.close(self)


def _order(row: sqlite3.Row) -> Order:
    return Order(
        row["id"],
        row["part_type"],
        row["qty"],
        row["priority"],
        row["state"],
        row["created"],
        row["updated"],
        row["note"],
    )


def _report(row: sqlite3.Row) -> Report:
    return Report(
        row["seq"],
        row["time"],
        row["kind"],
        row["order_id"],
        row["part_id"],
        row["text"],
        json.loads(row["data"]),
    )
