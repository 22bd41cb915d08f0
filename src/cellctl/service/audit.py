"""The audit trail: who did what, when, and how it ended, in the cell's journal file (its own
table ``audit``, made if missing, so an older journal keeps working)::

    with AuditLog(Path("cell")) as log:
        log.record("ann", "orders.submit", {"part_type": "base"}, "ok")
        for entry in log.entries(since=time.time() - 3600, who="ann"):
            print(entry.at, entry.who, entry.method, entry.result)

Who is a token's name (``token:ann``), an OPC UA user (``opcua:bob``) or the local user of a
CLI call that ran in-process (``local:alice``). What is the method and its parameters as
JSON, cut to :data:`MAX_PARAMS` characters; the result is ``ok``, ``cancelled`` (cut short
before its end) or the error's text.

The table is bounded, so that no caller can fill the disk with it: it keeps the newest
:data:`KEEP_OK` entries of calls that succeeded and, apart, the newest :data:`KEEP_OTHER`
of the others (refused, failed, cancelled): a flood of refusals never pushes out what was
done. A refusal that repeats the same caller's last one of that method, within
:data:`COLLAPSE_S` s, is counted on it (``repeats``, ``last_at``) instead of adding one.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
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

SCHEMA = """
CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    at REAL NOT NULL,
    who TEXT NOT NULL,
    method TEXT NOT NULL,
    params TEXT NOT NULL,
    result TEXT NOT NULL,
    repeats INTEGER NOT NULL DEFAULT 1,
    last_at REAL
);
CREATE INDEX IF NOT EXISTS audit_by_at ON audit (at);
CREATE INDEX IF NOT EXISTS audit_by_caller ON audit (who, method, id);
"""
#: Columns a journal from before they were added gains when it is opened.
_ADDED = {"repeats": "INTEGER NOT NULL DEFAULT 1", "last_at": "REAL"}


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
        """Give a table from before ``repeats`` and ``last_at`` its new columns."""
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
        """Add one entry: ``result`` is ``"ok"``, ``"cancelled"`` or the error's text.
        ``collapse`` (a refusal): if the caller's last entry of ``method`` is the same
        refusal, its last repeat at most :data:`COLLAPSE_S` s ago, it is counted there."""
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
            cur = db.execute(
                "INSERT INTO audit (at, who, method, params, result) VALUES (?, ?, ?, ?, ?)", row
            )
            if self._records % PRUNE_EVERY == 0:
                self._prune(db)
            self._records += 1
        return AuditEntry(int(cur.lastrowid or 0), *row)

    def _prune(self, db: Any) -> None:
        """Keep the newest ``keep_ok`` entries that say ``ok`` and the newest ``keep_other``
        of the rest; delete what is older."""
        for test, keep in (("=", self.keep_ok), ("!=", self.keep_other)):
            edge = db.execute(
                f"SELECT id FROM audit WHERE result {test} 'ok' ORDER BY id DESC LIMIT 1 OFFSET ?",
                (keep,),
            ).fetchone()
            if edge is not None:
                db.execute(f"DELETE FROM audit WHERE result {test} 'ok' AND id <= ?", (edge[0],))

    def entries(
        self, *, since: float | None = None, who: str | None = None, limit: int = 200
    ) -> list[AuditEntry]:
        """The last ``limit`` entries (oldest first), since a time, by one caller."""
        where: list[str] = []
        args: list[Any] = []
        if since is not None:
            where.append("at >= ?")
            args.append(since)
        if who is not None:
            where.append("(who = ? OR substr(who, instr(who, ':') + 1) = ?)")
            args += [who, who]
        sql = "SELECT * FROM audit" + (" WHERE " + " AND ".join(where) if where else "")
        sql += " ORDER BY id DESC LIMIT ?"
        rows = self._read(sql, [*args, max(1, min(limit, MAX_ENTRIES))])
        return [AuditEntry(**dict(r)).shown() for r in reversed(rows)]
