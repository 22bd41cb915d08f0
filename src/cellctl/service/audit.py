"""The audit trail: who did what, when, and how it ended, in the cell's journal file (its own
table ``audit``, made if missing, so an older journal keeps working)::

    with AuditLog(Path("cell")) as log:
        log.record("ann", "orders.submit", {"part_type": "base"}, "ok")
        for entry in log.entries(since=time.time() - 3600, who="ann"):
            print(entry.at, entry.who, entry.method, entry.result)

Who is a token's name (``token:ann``), an OPC UA user (``opcua:bob``) or the local user of a
CLI call that ran in-process (``local:alice``). What is the method and its parameters as
JSON, cut to :data:`MAX_PARAMS` characters; the result is ``running`` while an acting call
runs, then ``ok``, ``cancelled`` (cut short before its end), the error's text, or
:data:`INTERRUPTED` ("interrupted: ...", see below).

An acting call is written as it begins, so that a call cut by a crash is still on record, at
the time it began (an emergency stop that waited 10 s for a mill is listed when it was
pressed)::

    entry = log.begin("token:ann", "mill.download", {"machine": "cnc2"})  # result "running"
    ...                                                                  # the call runs
    log.end(entry, "ok")          # the same row: its result, and when it ``ended``

An entry still :data:`RUNNING` when the cell's controller starts again was cut by a crash, a
kill or a power cut: that controller, holding the cell (and only it: a CLI reading the trail
while a controller runs must not touch the controller's calls in flight), marks it
:data:`INTERRUPTED` (:func:`mark_interrupted`): what the call did is unknown.
Refusals and token changes are decided at once, and written whole (:meth:`AuditLog.record`).

The table is bounded, so that no caller can fill the disk with it: it keeps the newest
:data:`KEEP_OK` entries of calls that succeeded and, apart, the newest :data:`KEEP_OTHER`
of the others (refused, failed, cancelled, interrupted): a flood of refusals never pushes
out what was done. An entry still running is never pruned (see :meth:`AuditLog._prune`).
A refusal that repeats the same caller's last one of that method, within
:data:`COLLAPSE_S` s, is counted on it (``repeats``, ``last_at``) instead of adding one.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import Any

from cellctl.cell.journal import JOURNAL_FILE
from cellctl.cell.sqlitedb import SqliteStore
from cellctl.clock import Clock, current_clock

#: The most characters of a call's parameters (as JSON) kept; more is cut with "…".
MAX_PARAMS = 500
#: The most characters of an error's text kept.
MAX_RESULT = 300
#: The most entries one listing answers.
MAX_ENTRIES = 10_000
#: Entries of calls that succeeded (``ok``) kept: the newest; older ones are pruned.
KEEP_OK = 50_000
#: Entries of calls refused, failed or cancelled kept, apart from those that succeeded.
KEEP_OTHER = 10_000
#: The table is pruned at a log's first entry, then at every this many.
PRUNE_EVERY = 200
#: A refusal repeating the same caller's last one of a method (the same text) within this
#: many seconds of its last repeat is counted on that entry ...
COLLAPSE_S = 60.0
#: ... as long as that entry is no older than this (one entry per caller's refusals an hour).
COLLAPSE_SPAN = 3600.0
#: The result of an acting call's entry while the call runs (:meth:`AuditLog.begin`).
RUNNING = "running"
#: The result of an entry found :data:`RUNNING` when the cell's controller starts again.
INTERRUPTED = (
    "interrupted: the process serving the call stopped before it ended (a crash, a kill, "
    "a power cut): what it did is unknown"
)

SCHEMA = """
CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    at REAL NOT NULL,
    who TEXT NOT NULL,
    method TEXT NOT NULL,
    params TEXT NOT NULL,
    result TEXT NOT NULL,
    repeats INTEGER NOT NULL DEFAULT 1,
    last_at REAL,
    ended REAL
);
CREATE INDEX IF NOT EXISTS audit_by_at ON audit (at);
CREATE INDEX IF NOT EXISTS audit_by_caller ON audit (who, method, id);
"""
#: Columns a journal from before they were added gains when it is opened.
_ADDED = {"repeats": "INTEGER NOT NULL DEFAULT 1", "last_at": "REAL", "ended": "REAL"}


def keeps_trail(directory: Path) -> bool:
    """Whether ``directory`` is a cell whose actions are audited: it has a journal, or a
    cell.toml (a cell that has not run yet: its first entry makes the journal). A directory
    that is neither gets no journal made for it."""
    return (directory / JOURNAL_FILE).is_file() or (directory / "cell.toml").is_file()


@dataclass(frozen=True)
class AuditEntry:
    id: int
    at: float
    who: str
    method: str
    params: str
    result: str
    #: How many times it happened: a refusal repeated is counted here (:data:`COLLAPSE_S`).
    repeats: int = 1
    #: When the last repeat was (None: it happened once).
    last_at: float | None = None
    #: When a call written as it began ended (None: still running, or interrupted; or an
    #: entry written whole: a refusal, a token change, one from before the column).
    ended: float | None = None

    @classmethod
    def running(cls, who: str, method: str, params: Any, at: float) -> AuditEntry:
        """The entry of an acting call beginning at ``at`` (not written yet: ``id`` 0)."""
        return cls(0, at, _cut(who, 100), _cut(method, 100), params_text(params), RUNNING)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def shown(self) -> AuditEntry:
        """The entry as listed: a repeated one says so in its result."""
        if self.repeats <= 1:
            return self
        span = max(0.0, (self.last_at or self.at) - self.at)
        more = f" (and {self.repeats - 1} times more in the next {span:.0f} s)"
        return replace(self, result=self.result + more)


def _cut(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"


def params_text(params: Any) -> str:
    """``params`` as compact JSON, bounded (what a caller hands us may be anything)."""
    try:
        text = json.dumps(params, default=str, sort_keys=True, separators=(",", ":"))
    except (ValueError, TypeError, RecursionError):  # nested past what JSON can write
        text = f"<{type(params).__name__} too deep to show>"
    return _cut(text, MAX_PARAMS)


class AuditLog(SqliteStore):
    """The audit table of ``<cell>/journal.sqlite3`` (see module docstring)."""

    def __init__(
        self,
        cell_dir: Path,
        *,
        clock: Clock | None = None,
        keep_ok: int = KEEP_OK,
        keep_other: int = KEEP_OTHER,
    ) -> None:
        super().__init__(Path(cell_dir) / JOURNAL_FILE, SCHEMA)
        self._clock = clock
        self.keep_ok = keep_ok
        self.keep_other = keep_other
        self._records = 0
        self._add_columns()

    def _add_columns(self) -> None:
        """Give a table from before ``repeats``, ``last_at`` and ``ended`` its new columns."""
        if set(_ADDED) <= {r["name"] for r in self._read("PRAGMA table_info(audit)")}:
            return
        with self._write() as db:  # another process may have added them meanwhile
            have = {r["name"] for r in db.execute("PRAGMA table_info(audit)")}
            for name, kind in _ADDED.items():
                if name not in have:
                    db.execute(f"ALTER TABLE audit ADD COLUMN {name} {kind}")

    def record(
        self, who: str, method: str, params: Any, result: str, *, collapse: bool = False
    ) -> AuditEntry:
        """Add one entry, whole (a refusal, a token change: decided at once; an acting call
        of the API is written as it begins, :meth:`begin`): ``result`` is ``"ok"`` or the
        error's text. ``collapse`` (a refusal): if the caller's last entry of ``method`` is
        the same refusal, its last repeat at most :data:`COLLAPSE_S` s ago, it is counted
        there."""
        now = (self._clock or current_clock()).now()
        row = (
            now,
            _cut(who, 100),
            _cut(method, 100),
            params_text(params),
            _cut(result, MAX_RESULT),
        )
        with self._write() as db:
            if collapse:
                last = db.execute(
                    "SELECT * FROM audit WHERE who = ? AND method = ? ORDER BY id DESC LIMIT 1",
                    row[1:3],
                ).fetchone()
                if (
                    last is not None
                    and last["result"] == row[4]
                    and now - (last["last_at"] or last["at"]) <= COLLAPSE_S
                    and now - last["at"] <= COLLAPSE_SPAN
                ):
                    db.execute(
                        "UPDATE audit SET repeats = repeats + 1, last_at = ? WHERE id = ?",
                        (now, last["id"]),
                    )
                    return replace(
                        AuditEntry(**dict(last)), repeats=last["repeats"] + 1, last_at=now
                    )
            entry_id = self._insert(db, row)
        return AuditEntry(entry_id, *row)

    def _insert(self, db: Any, row: tuple[Any, ...], ended: float | None = None) -> int:
        cur = db.execute(
            "INSERT INTO audit (at, who, method, params, result, ended) VALUES (?, ?, ?, ?, ?, ?)",
            (*row, ended),
        )
        if self._records % PRUNE_EVERY == 0:
            self._prune(db)
        self._records += 1
        return int(cur.lastrowid or 0)

    def begin(self, who: str, method: str, params: Any, *, at: float | None = None) -> AuditEntry:
        """Write an acting call as it begins (at ``at``, now by default): its result
        :data:`RUNNING` until :meth:`end` gives it the outcome, on the same row."""
        now = (self._clock or current_clock()).now() if at is None else at
        entry = AuditEntry.running(who, method, params, now)
        with self._write() as db:
            entry_id = self._insert(db, (now, entry.who, entry.method, entry.params, RUNNING))
        return replace(entry, id=entry_id)

    def end(self, entry: AuditEntry, result: str) -> AuditEntry:
        """The call ``entry`` (from :meth:`begin`) ended: ``result`` is ``"ok"``,
        ``"cancelled"`` or the error's text, and ``ended`` now; its ``at`` stays when it
        began. An entry whose row is not there (its first write failed: ``id`` 0) is written
        whole."""
        now = (self._clock or current_clock()).now()
        result = _cut(result, MAX_RESULT)
        with self._write() as db:
            # Whatever the row says now: a controller starting meanwhile may have taken a
            # running call of a CLI in-process for one cut by a crash; its end says the truth.
            found = db.execute(
                "UPDATE audit SET result = ?, ended = ? WHERE id = ?", (result, now, entry.id)
            ).rowcount
            if not found:
                row = (entry.at, entry.who, entry.method, entry.params, result)
                entry = replace(entry, id=self._insert(db, row, ended=now))
        return replace(entry, result=result, ended=now)

    def mark_interrupted(self) -> list[AuditEntry]:
        """Mark every entry still :data:`RUNNING` :data:`INTERRUPTED`, and return them.

        Only the cell's controller calls this, as it starts, holding the cell's controller
        lock (``cellctl run``): no call of its own runs yet, so an entry still running was
        cut by the end of the process that served it. Any other process opening the log
        (``cellctl audit``, a command that reads the journal) leaves the entries alone: a
        controller running meanwhile is still serving them."""
        with self._write() as db:
            rows = db.execute("SELECT * FROM audit WHERE result = ? ORDER BY id", (RUNNING,))
            found = [replace(AuditEntry(**dict(r)), result=INTERRUPTED) for r in rows.fetchall()]
            db.execute("UPDATE audit SET result = ? WHERE result = ?", (INTERRUPTED, RUNNING))
        return found

    def _prune(self, db: Any) -> None:
        """Keep the newest ``keep_ok`` entries that say ``ok`` and the newest ``keep_other``
        of the rest; delete what is older.

        An entry still running is neither, and never deleted: its call's end must find its
        row (a flood of refusals must not push out a download under way), and there are
        never more of them than calls in flight (the API caps those) plus the ones a crash
        left, which the next controller marks interrupted (an "other" from then on)."""
        kinds: list[tuple[str, tuple[str, ...], int]] = [
            ("result = 'ok'", (), self.keep_ok),
            ("result NOT IN ('ok', ?)", (RUNNING,), self.keep_other),
        ]
        for test, args, keep in kinds:
            edge = db.execute(
                f"SELECT id FROM audit WHERE {test} ORDER BY id DESC LIMIT 1 OFFSET ?",
                (*args, keep),
            ).fetchone()
            if edge is not None:
                db.execute(f"DELETE FROM audit WHERE {test} AND id <= ?", (*args, edge[0]))

    def entries(
        self, *, since: float | None = None, who: str | None = None, limit: int = 200
    ) -> list[AuditEntry]:
        """The last ``limit`` entries (oldest first, by when they began), since a time, by
        one caller."""
        where: list[str] = []
        args: list[Any] = []
        if since is not None:
            where.append("at >= ?")
            args.append(since)
        if who is not None:
            where.append("(who = ? OR substr(who, instr(who, ':') + 1) = ?)")
            args += [who, who]
        sql = "SELECT * FROM audit" + (" WHERE " + " AND ".join(where) if where else "")
        # By when they began: two calls beginning together may be written in either order.
        sql += " ORDER BY at DESC, id DESC LIMIT ?"
        rows = self._read(sql, [*args, max(1, min(limit, MAX_ENTRIES))])
        return [AuditEntry(**dict(r)).shown() for r in reversed(rows)]


def interrupted_note(entry: AuditEntry) -> str:
    """What the controller's event log says of an entry it marked :data:`INTERRUPTED`."""
    began = datetime.fromtimestamp(entry.at).strftime("%Y-%m-%d %H:%M:%S")
    return (
        f"audit: {entry.method} by {entry.who}, begun {began}, had not ended when the "
        "process serving it stopped: marked interrupted (what it did is unknown: look at "
        "what it drove before using it)"
    )


def mark_interrupted(cell_dir: Path) -> list[AuditEntry]:
    """The entries of ``cell_dir``'s trail still running, marked :data:`INTERRUPTED`: for the
    cell's controller only, as it starts, holding the cell's controller lock (see
    :meth:`AuditLog.mark_interrupted`). A directory that keeps no trail has none."""
    if not (Path(cell_dir) / JOURNAL_FILE).is_file():
        return []
    with AuditLog(cell_dir) as log:
        return log.mark_interrupted()
