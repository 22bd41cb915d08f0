"""The audit trail: who did what, when, and how it ended, in the cell's journal file (its own
table ``audit``, made if missing, so an older journal keeps working)::

    with AuditLog(Path("cell")) as log:
        log.record("ann", "orders.submit", {"part_type": "base"}, "ok")
        for entry in log.entries(since=time.time() - 3600, who="ann"):
            print(entry.at, entry.who, entry.method, entry.result)

Who is a token's name (``token:ann``), an OPC UA user (``opcua:bob``) or the local user of a
CLI call that ran in-process (``local:alice``). What is the method and its parameters as
JSON, cut to :data:`MAX_PARAMS` characters; the result is ``ok`` or the error's text.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
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

SCHEMA = """
CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    at REAL NOT NULL,
    who TEXT NOT NULL,
    method TEXT NOT NULL,
    params TEXT NOT NULL,
    result TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS audit_by_at ON audit (at);
"""


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

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


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

    def __init__(self, cell_dir: Path, *, clock: Clock | None = None) -> None:
        super().__init__(Path(cell_dir) / JOURNAL_FILE, SCHEMA)
        self._clock = clock

    def record(self, who: str, method: str, params: Any, result: str) -> AuditEntry:
        """Add one entry: ``result`` is ``"ok"`` or the error's text."""
        row = (
            (self._clock or current_clock()).now(),
            _cut(who, 100),
            _cut(method, 100),
            params_text(params),
            _cut(result, MAX_RESULT),
        )
        with self._write() as db:
            cur = db.execute(
                "INSERT INTO audit (at, who, method, params, result) VALUES (?, ?, ?, ?, ?)", row
            )
        return AuditEntry(int(cur.lastrowid or 0), *row)

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
        return [AuditEntry(**dict(r)) for r in reversed(rows)]
