"""The journal's alarms (ISA-18.2 states), in :class:`AlarmJournal`, the base class of
:class:`~cellctl.cell.journal.Journal`; use them through the journal::

    alarm, new = journal.raise_alarm("cnc1", "link", "cnc1 does not answer")
    journal.ack_alarm(alarm.id, by="ann")        # seen; still open
    journal.shelve_alarm(alarm.id, 3600, "ann")  # not shown as unacknowledged for 1 h ...
    journal.unshelve_alarm(alarm.id, by="ann")   # ... or shown as it is again at once
    journal.return_to_normal("cnc1", ["link"])   # its condition is gone; still open
    journal.clear_alarm(alarm.id, by="ann")      # ended
    journal.alarm_spells()[alarm.id]             # [Spell(began, ended)]: when it was active

An alarm is raised active and unacknowledged, may be shelved for at most :data:`MAX_SHELVE`
(unshelved sooner by the operator), and stays open until the operator clears it. Its
condition may go and come back while it is open (returned to normal, then active again: the
same alarm); the alarm's row keeps only the last return, so each time it was active is kept
apart, as a spell (table ``alarm_spells``): from raised or active again, to returned to
normal, else to cleared. The shift report's down time counts these. A journal from before
spells has its alarms count as one spell each (raised to returned, else cleared); the first
change of such an alarm writes that spell before its own. The base also holds what these
need of the journal: the clock its times are read from and its in-memory views
(:mod:`cellctl.cell.journalview`).
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Final

from cellctl.cell.causes import PRIORITIES, priority_of
from cellctl.cell.journalrecords import Alarm, Spell
from cellctl.cell.journalview import JournalViews
from cellctl.cell.sqlitedb import SqliteStore
from cellctl.clock import Clock, current_clock
from cellctl.errors import UsageError

__all__ = ["MAX_SHELVE", "AlarmJournal"]

#: The alarm columns added after the first journals (ISA-18.2 states): an older journal gets
#: them on open, with defaults that read as "acknowledged nothing, still seen, not shelved".
_ALARM_COLUMNS: Final = (
    ("priority", "TEXT NOT NULL DEFAULT 'medium'"),
    ("acked", "REAL"),
    ("acked_by", "TEXT NOT NULL DEFAULT ''"),
    ("returned", "REAL"),
    ("shelved_until", "REAL"),
    ("shelved_by", "TEXT NOT NULL DEFAULT ''"),
)
#: The longest an alarm may be shelved, s (8 h: one shift).
MAX_SHELVE: Final = 8 * 3600.0


class AlarmJournal(SqliteStore):
    """The alarms of the journal in ``path`` (whose ``schema`` has the ``alarms`` table), its
    clock and its in-memory views; open a :class:`~cellctl.cell.journal.Journal`, which adds
    the parts, steps and machines."""

    def __init__(
        self, path: Path, schema: str, *, clock: Clock | None = None, durable: bool = True
    ) -> None:
        super().__init__(path, schema, durable=durable)
        self._clock = clock
        self._views = JournalViews()
        self._migrate_alarms()

    @property
    def clock(self) -> Clock:
        """What the journal's times are read from: the clock given, else the running loop's."""
        return self._clock or current_clock()

    def _now(self) -> float:
        return self.clock.now()

    def _viewed(self) -> JournalViews:
        """The views, current (hold ``self._lock``)."""
        self._views_current()
        return self._views

    def _keep_alarm(self, alarm: Alarm) -> Alarm:
        self._after_commit(lambda: self._views.alarm(alarm))
        return alarm

    def _migrate_alarms(self) -> None:
        """Add the alarm columns a journal from before alarm states lacks (idempotent)."""
        have = {r["name"] for r in self._read("PRAGMA table_info(alarms)")}
        missing = [(name, kind) for name, kind in _ALARM_COLUMNS if name not in have]
        if not missing:
            return
        with self._write() as db:
            have = {r["name"] for r in db.execute("PRAGMA table_info(alarms)")}
            for name, kind in missing:
                if name not in have:  # another process may have added it meanwhile
                    db.execute(f"ALTER TABLE alarms ADD COLUMN {name} {kind}")
            for code in {r["code"] for r in db.execute("SELECT DISTINCT code FROM alarms")}:
                db.execute(
                    "UPDATE alarms SET priority = ? WHERE code = ?", (priority_of(code), code)
                )

    # -- alarms ------------------------------------------------------------------------------

    def raise_alarm(self, machine: str, code: str, text: str) -> tuple[Alarm, bool]:
        """Raise an alarm; return it and whether it is new (an identical active alarm,
        same machine, code and text, is returned instead of raising a second one; if it had
        returned to normal its condition is back: active and unacknowledged again)."""
        now = self._now()
        with self._write() as db:
            row = db.execute(
                "SELECT * FROM alarms WHERE state = 'active' AND machine = ? AND code = ?"
                " AND text = ? ORDER BY id LIMIT 1",
                (machine, code, text),
            ).fetchone()
            if row is not None:
                if row["returned"] is None:
                    return _alarm(row), False
                return self._reactivate(db, row["id"], now), False
            cur = db.execute(
                "INSERT INTO alarms (raised, machine, code, text, state, priority)"
                " VALUES (?, ?, ?, ?, 'active', ?)",
                (now, machine, code, text, priority_of(code)),
            )
            alarm_id = cur.lastrowid
            assert alarm_id is not None
            _spell_begins(db, alarm_id, now)
            return self._keep_alarm(_get_alarm(db, alarm_id)), True

    def reactivate(self, alarm_id: int) -> Alarm:
        """The condition of open alarm ``alarm_id`` is seen again after it returned to
        normal: active and unacknowledged again, a new spell begun (a cleared or still-active
        alarm: unchanged)."""
        now = self._now()
        with self._write() as db:
            alarm = _get_alarm(db, alarm_id)
            if alarm.state != "active" or alarm.returned is None:
                return alarm
            return self._reactivate(db, alarm_id, now)

    def _reactivate(self, db: sqlite3.Connection, alarm_id: int, now: float) -> Alarm:
        _spells_kept(db, alarm_id)  # first: an older alarm's one spell ends at its return
        _spell_begins(db, alarm_id, now)
        db.execute(
            "UPDATE alarms SET returned = NULL, acked = NULL, acked_by = '' WHERE id = ?",
            (alarm_id,),
        )
        return self._keep_alarm(_get_alarm(db, alarm_id))

    def ack_alarm(self, alarm_id: int, by: str = "operator") -> Alarm:
        """Acknowledge an alarm: the operator has seen it (it stays open until cleared).
        Already acknowledged or cleared: changes nothing."""
        with self._write() as db:
            alarm = _get_alarm(db, alarm_id)
            if alarm.acked is not None or alarm.state == "cleared":
                return alarm
            db.execute(
                "UPDATE alarms SET acked = ?, acked_by = ? WHERE id = ?",
                (self._now(), by, alarm_id),
            )
            return self._keep_alarm(_get_alarm(db, alarm_id))

    def shelve_alarm(self, alarm_id: int, seconds: float, by: str = "operator") -> Alarm:
        """Shelve an open alarm for ``seconds`` (0 < seconds <= :data:`MAX_SHELVE`): not shown
        as unacknowledged until then. Shelving again sets a new end."""
        if not 0 < seconds <= MAX_SHELVE:
            raise UsageError(
                f"shelve for more than 0 s and at most {MAX_SHELVE / 3600:g} h, not {seconds:g} s"
            )
        with self._write() as db:
            alarm = _get_alarm(db, alarm_id)
            if alarm.state == "cleared":
                raise UsageError(f"alarm {alarm_id} is cleared: nothing to shelve")
            db.execute(
                "UPDATE alarms SET shelved_until = ?, shelved_by = ? WHERE id = ?",
                (self._now() + seconds, by, alarm_id),
            )
            return self._keep_alarm(_get_alarm(db, alarm_id))

    def unshelve_alarm(self, alarm_id: int, by: str = "operator") -> Alarm:
        """Unshelve an alarm shelved now: shown as it is again at once (unacknowledged, if
        it was not acknowledged). Refused for a cleared alarm, and for one not shelved now
        (never, or its time ran out). ``by`` unshelves it: the row keeps no unshelver (its
        ``shelved_by`` is emptied); the API's audit trail names the caller."""
        with self._write() as db:
            alarm = _get_alarm(db, alarm_id)
            if alarm.state == "cleared":
                raise UsageError(f"alarm {alarm_id} is cleared: nothing to unshelve")
            if not alarm.shelved(self._now()):
                raise UsageError(f"alarm {alarm_id} is not shelved")
            db.execute(
                "UPDATE alarms SET shelved_until = NULL, shelved_by = '' WHERE id = ?", (alarm_id,)
            )
            return self._keep_alarm(_get_alarm(db, alarm_id))

    def return_to_normal(self, machine: str, codes: Iterable[str]) -> list[Alarm]:
        """The condition behind ``machine``'s open alarms with these codes is gone: mark them
        returned to normal (they stay open until cleared), their spell ended. Returns the
        alarms it marked; a look that finds nothing to mark writes nothing."""
        codes = tuple(codes)
        marks = ",".join("?" * len(codes))
        query = (
            "SELECT id FROM alarms WHERE state = 'active' AND returned IS NULL"
            f" AND machine = ? AND code IN ({marks})"
        )
        if not codes or not self._read(query, (machine, *codes)):
            return []
        with self._write() as db:
            ids = [r["id"] for r in db.execute(query, (machine, *codes))]
            now = self._now()
            for i in ids:
                _spell_ends(db, i, now)
            db.executemany("UPDATE alarms SET returned = ? WHERE id = ?", [(now, i) for i in ids])
            return [self._keep_alarm(_get_alarm(db, i)) for i in ids]

    def clear_alarm(self, alarm_id: int, by: str = "operator") -> Alarm:
        """Clear an alarm: the operator's action that ends it (acknowledging it too, if it
        was not). Already cleared: changes nothing."""
        with self._write() as db:
            alarm = _get_alarm(db, alarm_id)
            if alarm.state == "cleared":
                return alarm
            now = self._now()
            _spell_ends(db, alarm_id, now)  # still active: its spell ends here
            db.execute(
                "UPDATE alarms SET state = 'cleared', cleared = ?, cleared_by = ?,"
                " acked = coalesce(acked, ?),"
                " acked_by = CASE WHEN acked IS NULL THEN ? ELSE acked_by END WHERE id = ?",
                (now, by, now, by, alarm_id),
            )
            return self._keep_alarm(_get_alarm(db, alarm_id))

    def get_alarm(self, alarm_id: int) -> Alarm:
        """The alarm ``alarm_id``."""
        with self._lock:
            alarm = self._viewed().alarms.get(alarm_id)
        if alarm is None:
            raise UsageError(f"no alarm {alarm_id}")
        return alarm

    def active_alarms(self) -> list[Alarm]:
        """Alarms not cleared yet, oldest first."""
        with self._lock:
            return self._viewed().active_alarms()

    def open_alarm(self, machine: str, code: str) -> Alarm | None:
        """``machine``'s oldest alarm with ``code`` not cleared yet, or None."""
        return next(
            (a for a in self.active_alarms() if a.machine == machine and a.code == code), None
        )

    def alarms(self) -> list[Alarm]:
        """Every alarm, oldest first."""
        with self._lock:
            return list(self._viewed().alarms.values())

    def alarm_spells(self, alarms: Iterable[Alarm] | None = None) -> dict[int, list[Spell]]:
        """When each of ``alarms`` (default: every alarm) was active, by its id: its spells,
        oldest first. A spell still open when its alarm was cleared ends there; one still
        open ends None. An alarm from before spells were kept has one: raised to returned to
        normal, else to cleared (what its own columns say)."""
        alarms = self.alarms() if alarms is None else list(alarms)
        kept: dict[int, list[Spell]] = {}
        for r in self._read(
            "SELECT alarm_id, began, ended FROM alarm_spells ORDER BY alarm_id, began, rowid"
        ):
            kept.setdefault(r["alarm_id"], []).append(Spell(r["began"], r["ended"]))
        out: dict[int, list[Spell]] = {}
        for a in alarms:
            spells = kept.get(a.id)
            if not spells:
                out[a.id] = [Spell(a.raised, a.returned if a.returned is not None else a.cleared)]
            else:
                out[a.id] = [
                    Spell(s.began, s.ended if s.ended is not None else a.cleared) for s in spells
                ]
        return out

    def alarm_history(
        self,
        *,
        since: float | None = None,
        machine: str | None = None,
        priority: str | None = None,
        limit: int = 1000,
    ) -> list[Alarm]:
        """Alarms raised since ``since`` (s), on ``machine``, of ``priority``; oldest first,
        the newest ``limit`` of them."""
        if priority is not None and priority not in PRIORITIES:
            raise UsageError(f"priority {priority!r}: one of {', '.join(PRIORITIES)}")
        where: list[str] = ["1"]
        args: list[Any] = []
        if since is not None:
            where.append("raised >= ?")
            args.append(since)
        if machine is not None:
            where.append("machine = ?")
            args.append(machine)
        if priority is not None:
            where.append("priority = ?")
            args.append(priority)
        rows = self._read(
            f"SELECT * FROM alarms WHERE {' AND '.join(where)} ORDER BY id DESC LIMIT ?",
            (*args, limit),
        )
        return [_alarm(r) for r in reversed(rows)]


def _spell_begins(db: sqlite3.Connection, alarm_id: int, now: float) -> None:
    """Inside a write: alarm ``alarm_id`` is active from ``now`` (raised, or active again:
    :func:`_spells_kept` first)."""
    db.execute(
        "INSERT INTO alarm_spells (alarm_id, began, ended) VALUES (?, ?, NULL)", (alarm_id, now)
    )


def _spell_ends(db: sqlite3.Connection, alarm_id: int, now: float) -> None:
    """Inside a write: alarm ``alarm_id``'s open spell, if any, ends at ``now`` (returned to
    normal, or cleared while active)."""
    _spells_kept(db, alarm_id)
    db.execute(
        "UPDATE alarm_spells SET ended = ? WHERE alarm_id = ? AND ended IS NULL", (now, alarm_id)
    )


def _spells_kept(db: sqlite3.Connection, alarm_id: int) -> None:
    """Inside a write, before the alarm's row changes: an alarm from before spells were kept
    (it has none) gets the one its columns say (raised to returned, else cleared, else open),
    so that what the write adds follows it. (A new alarm's first spell is written with it.)"""
    db.execute(
        "INSERT INTO alarm_spells (alarm_id, began, ended)"
        " SELECT id, raised, coalesce(returned, cleared) FROM alarms WHERE id = ?"
        " AND NOT EXISTS (SELECT 1 FROM alarm_spells WHERE alarm_id = ?)",
        (alarm_id, alarm_id),
    )


def _get_alarm(db: sqlite3.Connection, alarm_id: int) -> Alarm:
    row = db.execute("SELECT * FROM alarms WHERE id = ?", (alarm_id,)).fetchone()
    if row is None:
        raise UsageError(f"no alarm {alarm_id}")
    return _alarm(row)


def _alarm(row: sqlite3.Row) -> Alarm:
    return Alarm(
        row["id"],
        row["raised"],
        row["machine"],
        row["code"],
        row["text"],
        row["state"],
        row["cleared"],
        row["cleared_by"],
        row["priority"],
        row["acked"],
        row["acked_by"],
        row["returned"],
        row["shelved_until"],
        row["shelved_by"],
    )
