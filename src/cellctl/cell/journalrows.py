"""The journal's SQLite tables (:data:`SCHEMA`) and the helpers that read a part's or a
step's row into its record (:mod:`cellctl.cell.journalrecords`) and update a part's row.

:class:`~cellctl.cell.journal.Journal` calls them inside its write transactions, e.g.
``part = _get_part(db, part_id)``; the alarms' rows are read in
:mod:`cellctl.cell.journalalarms`.
"""

from __future__ import annotations

import sqlite3
from typing import Any

from cellctl.cell.journalrecords import Part, Step
from cellctl.errors import UsageError

SCHEMA = """
CREATE TABLE IF NOT EXISTS parts (
    id TEXT PRIMARY KEY,
    order_id TEXT NOT NULL,
    part_type TEXT NOT NULL,
    seq_in_order INTEGER NOT NULL,
    route_index INTEGER NOT NULL DEFAULT 0,
    location TEXT NOT NULL,
    status TEXT NOT NULL,
    updated REAL NOT NULL,
    note TEXT NOT NULL DEFAULT '',
    held_step INTEGER
);
CREATE INDEX IF NOT EXISTS parts_by_order ON parts (order_id);
CREATE TABLE IF NOT EXISTS steps (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    part_id TEXT NOT NULL,
    kind TEXT NOT NULL,
    machine TEXT NOT NULL,
    program TEXT NOT NULL,
    route_index INTEGER NOT NULL,
    state TEXT NOT NULL,
    started REAL NOT NULL,
    ended REAL,
    outcome TEXT NOT NULL DEFAULT '',
    attempt INTEGER NOT NULL,
    resolution TEXT NOT NULL DEFAULT ''
);
CREATE INDEX IF NOT EXISTS steps_by_part ON steps (part_id);
CREATE INDEX IF NOT EXISTS steps_by_state ON steps (state);
CREATE TABLE IF NOT EXISTS alarms (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    raised REAL NOT NULL,
    machine TEXT NOT NULL,
    code TEXT NOT NULL,
    text TEXT NOT NULL,
    state TEXT NOT NULL,
    cleared REAL,
    cleared_by TEXT NOT NULL DEFAULT ''
);
CREATE INDEX IF NOT EXISTS alarms_by_state ON alarms (state);
-- Each alarm's active spells: from raised or active again to returned to normal, else to
-- cleared (ended NULL: still active). A journal from before spells gets the table empty on
-- open, and an alarm with no spell counts as one, raised to returned, else cleared (the
-- alarm's own columns, cellctl.cell.journalalarms). No semicolon in these comments: the
-- schema is run a statement at a time, split at them.
CREATE TABLE IF NOT EXISTS alarm_spells (
    alarm_id INTEGER NOT NULL,
    began REAL NOT NULL,
    ended REAL
);
CREATE INDEX IF NOT EXISTS alarm_spells_by_alarm ON alarm_spells (alarm_id);
CREATE TABLE IF NOT EXISTS machines (
    name TEXT PRIMARY KEY,
    in_service INTEGER NOT NULL,
    reason TEXT NOT NULL,
    updated REAL NOT NULL
);
-- Places the operator said are empty (a part scrapped, taken out of them) while their
-- vise may still be closed: the cell opens it before it loads them (docs/cell.md).
CREATE TABLE IF NOT EXISTS emptied (
    place TEXT PRIMARY KEY,
    part_id TEXT NOT NULL,
    since REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS service_log (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    time REAL NOT NULL,
    name TEXT NOT NULL,
    in_service INTEGER NOT NULL,
    reason TEXT NOT NULL
);
-- The controller's life: started, paused, resumed, stopped (the shift report's running,
-- paused and stopped time), by whom (a caller and their role) and why. A journal from
-- before it gets the table empty on open: that time is not known.
CREATE TABLE IF NOT EXISTS controller_log (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    time REAL NOT NULL,
    event TEXT NOT NULL,
    by TEXT NOT NULL DEFAULT '',
    why TEXT NOT NULL DEFAULT ''
);
"""


def _get_part(db: sqlite3.Connection, part_id: str) -> Part:
    row = db.execute("SELECT * FROM parts WHERE id = ?", (part_id,)).fetchone()
    if row is None:
        raise UsageError(f"no part {part_id!r}")
    return _part(row)


def _get_step(db: sqlite3.Connection, step_id: int) -> Step:
    row = db.execute("SELECT * FROM steps WHERE id = ?", (step_id,)).fetchone()
    if row is None:
        raise UsageError(f"no step {step_id}")
    return _step(row)


def _held_step(db: sqlite3.Connection, part_id: str) -> Step | None:
    row = db.execute(
        "SELECT s.* FROM steps s JOIN parts p ON p.held_step = s.id WHERE p.id = ?", (part_id,)
    ).fetchone()
    return None if row is None else _step(row)


_PART_COLUMNS = ("status", "location", "route_index", "note", "held_step")


def _update_part(db: sqlite3.Connection, part: Part, now: float, **changes: Any) -> Part:
    assert set(changes) <= set(_PART_COLUMNS), changes
    sets = ", ".join(f"{column} = ?" for column in changes)
    db.execute(
        f"UPDATE parts SET {sets}, updated = ? WHERE id = ?",
        (*changes.values(), now, part.id),
    )
    return _get_part(db, part.id)


def _part(row: sqlite3.Row) -> Part:
    return Part(
        row["id"],
        row["order_id"],
        row["part_type"],
        row["seq_in_order"],
        row["route_index"],
        row["location"],
        row["status"],
        row["updated"],
        row["note"],
    )


def _step(row: sqlite3.Row) -> Step:
    return Step(
        row["id"],
        row["part_id"],
        row["kind"],
        row["machine"],
        row["program"],
        row["state"],
        row["started"],
        row["ended"],
        row["outcome"],
        row["attempt"],
        row["route_index"],
        row["resolution"],
    )
