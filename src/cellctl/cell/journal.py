"""The cell controller's durable memory: parts, steps, alarms, machines in service, mills
emptied by hand.

``<cell_dir>/journal.sqlite3`` (SQLite, WAL). Every method is one short transaction,
committed and synced before it returns, so the controller may be killed at any instant and
the journal still tells the truth about everything that returned. The CLI opens the same
file at the same time for the operator's actions (release, scrap, clear an alarm); those
are journal facts the controller sees on its next read.

How the controller uses it::

    journal = open_journal(cell_dir)
    report = journal.recover()               # first thing at start: what a crash left
    parts = journal.create_parts(order)      # idempotent per order
    step = journal.begin_step(part.id, "machine", "cnc1", "ROUGH1")   # committed first,
    ...                                                                # then run the step
    journal.end_step(step.id, "finished", route_index=part.route_index + 1)

Rules that keep a restart from losing or repeating work:

* A part has at most one step in flight: ``begin_step`` makes it ``active``, ``end_step``
  makes it ``waiting`` again (or ``held``, with ``hold=``) in the same transaction, together
  with the new ``location``/``route_index`` the step produced.
* ``recover()`` marks every step still ``started`` as ``interrupted`` and holds its part:
  an interrupted machining step may have cut half a part, an interrupted transfer may have
  left it in the gripper. Nothing in flight is ever restarted automatically.
* The operator releases a held part (the step counts as done, unless ``redo_step``) or
  scraps it. :meth:`Journal.step_done` is what the controller asks before running a step.
  A part scrapped out of a mill (``taken_out_of``) leaves that mill emptied
  (:meth:`Journal.emptied_places`) until its vise is open: :mod:`cellctl.cell.vises`.

What the controller reads every round (parts, done steps, alarms, machines out of service)
is answered from in-memory views (:mod:`cellctl.cell.journalview`) that this journal's writes
keep current once committed and that are read again from the file after any other
connection commits: never an answer the file would not give.

The alarms (raise, acknowledge, shelve, unshelve, return to normal, clear, and the spells
they were active) live in :mod:`cellctl.cell.journalalarms`, the base class of
:class:`Journal`; the tables and the helpers that read their rows in
:mod:`cellctl.cell.journalrows`. Import from here as before.
"""

from __future__ import annotations

import functools
import sqlite3
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Final

from cellctl.cell.journalalarms import MAX_SHELVE, AlarmJournal, _alarm
from cellctl.cell.journalrecords import Alarm, Part, RecoveryReport, Spell, Step
from cellctl.cell.journalrows import (
    SCHEMA,
    _get_part,
    _get_step,
    _held_step,
    _part,
    _step,
    _update_part,
)
from cellctl.cell.journalview import JournalViews
from cellctl.cell.orders import OrderLike
from cellctl.clock import Clock
from cellctl.errors import UsageError

__all__ = [
    "CONTROLLER_EVENTS",
    "JOURNAL_FILE",
    "LOCATIONS",
    "MAX_SHELVE",
    "PART_STATUSES",
    "RESOLUTIONS",
    "STEP_KINDS",
    "STEP_STATES",
    "Alarm",
    "Journal",
    "Part",
    "RecoveryReport",
    "Spell",
    "Step",
    "open_journal",
]

#: The journal's file name inside the cell directory.
JOURNAL_FILE = "journal.sqlite3"

#: Where a part usually is. Any one-word name is accepted (the cell's machine names come from
#: ``cell.toml``); these are the names of the laboratory cell.
LOCATIONS: Final = ("conveyor", "robot", "cnc1", "cnc2", "out")
#: Part statuses: ``waiting`` (no step in flight), ``active`` (one step in flight), ``done``,
#: ``held`` (needs the operator: inspection after an interrupted or failed step), ``scrapped``,
#: ``cancelled`` (its order was cancelled before the part left the conveyor).
PART_STATUSES: Final = ("waiting", "active", "done", "held", "scrapped", "cancelled")
#: Step kinds: the robot moving a part between two places, or a mill cutting it.
STEP_KINDS: Final = ("transfer", "machine")
#: Step states: ``started`` (in flight), ``finished``, ``failed``, ``interrupted`` (was in
#: flight when the controller stopped; set by :meth:`Journal.recover`).
STEP_STATES: Final = ("started", "finished", "failed", "interrupted")
#: What the controller's log records (:meth:`Journal.note_controller`): it ``started``
#: (connecting), was ``paused`` (by a caller, or an emergency stop) and ``resumed``, ``stopped``.
CONTROLLER_EVENTS: Final = ("started", "paused", "resumed", "stopped")
#: What the operator decided about an interrupted or failed step of a held part.
RESOLUTIONS: Final = ("", "accepted", "redo")

INTERRUPTED_MACHINING = "needs inspection: machining step {program} on {machine} was interrupted"
INTERRUPTED_TRANSFER = "interrupted transfer: check the gripper and both stations"


def open_journal(cell_dir: Path, *, clock: Clock | None = None, durable: bool = True) -> Journal:
    """Open (creating if needed) ``<cell_dir>/journal.sqlite3`` (``durable=False``: a
    throwaway copy, e.g. a plan's, whose commits do not wait for the disk)."""
    return Journal(Path(cell_dir) / JOURNAL_FILE, clock=clock, durable=durable)


class Journal(AlarmJournal):
    """The journal in one SQLite file; use as a context manager or call :meth:`close`.

    Every method raises :class:`UsageError` for an unknown id or an action the part's state
    does not allow, and changes nothing then. ``clock`` gives the times it records (its
    ``now()``; None: the running loop's clock, read when a time is recorded).
    """

    def __init__(self, path: Path, *, clock: Clock | None = None, durable: bool = True) -> None:
        super().__init__(path, SCHEMA, clock=clock, durable=durable)

    def _load_views(self, db: sqlite3.Connection) -> None:
        views = JournalViews()
        for r in db.execute("SELECT rowid AS rank, * FROM parts ORDER BY rowid"):
            views.part(_part(r), r["rank"])
        for r in db.execute(
            "SELECT * FROM steps WHERE state = 'finished' OR resolution = 'accepted'"
        ):
            views.step(_step(r))
        for r in db.execute("SELECT * FROM alarms ORDER BY id"):
            views.alarm(_alarm(r))
        for r in db.execute("SELECT name, in_service, reason FROM machines"):
            views.machine(r["name"], bool(r["in_service"]), r["reason"])
        for r in db.execute("SELECT place, part_id FROM emptied"):
            views.emptied(r["place"], r["part_id"])
        self._views = views

    def _keep_part(self, part: Part, rank: int | None = None) -> Part:
        def apply() -> None:
            if not self._views.part(part, rank):
                self._views_at = None  # made by another connection: read everything again

        self._after_commit(apply)
        return part

    def _keep_step(self, step: Step) -> Step:
        self._after_commit(lambda: self._views.step(step))
        return step

    def _update(self, db: sqlite3.Connection, part: Part, now: float, **changes: Any) -> Part:
        return self._keep_part(_update_part(db, part, now, **changes))

    # -- parts -------------------------------------------------------------------------------

    def create_parts(self, order: OrderLike) -> list[Part]:
        """The parts of ``order`` (``<order id>-1`` .. ``-qty``), waiting on the conveyor.

        Idempotent: an order whose parts exist gets the same parts back, whatever they did.
        """
        if order.qty < 1:
            raise UsageError(f"order {order.id} has no parts to make (qty {order.qty})")
        now = self._now()
        with self._write() as db:
            rows = db.execute(
                "SELECT * FROM parts WHERE order_id = ? ORDER BY seq_in_order", (order.id,)
            ).fetchall()
            if rows:
                return [_part(r) for r in rows]
            parts = [
                Part(f"{order.id}-{n}", order.id, order.part_type, n, 0, "conveyor", "waiting", now)
                for n in range(1, order.qty + 1)
            ]
            db.executemany(
                "INSERT INTO parts (id, order_id, part_type, seq_in_order, route_index,"
                " location, status, updated) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                [
                    (p.id, p.order_id, p.part_type, p.seq_in_order, 0, p.location, p.status, now)
                    for p in parts
                ],
            )
            rows = db.execute(
                "SELECT rowid AS rank, * FROM parts WHERE order_id = ? ORDER BY rowid",
                (order.id,),
            ).fetchall()
            return [self._keep_part(_part(r), r["rank"]) for r in rows]

    def parts(
        self, statuses: Iterable[str] | None = None, order_id: str | None = None
    ) -> list[Part]:
        """Parts in creation order, only those in ``statuses`` / of ``order_id`` if given."""
        with self._lock:
            return self._viewed().select_parts(statuses, order_id)

    def get_part(self, part_id: str) -> Part:
        """The part ``part_id``."""
        with self._lock:
            part = self._viewed().parts.get(part_id)
        if part is None:
            raise UsageError(f"no part {part_id!r}")
        return part

    def move_part(self, part_id: str, location: str, route_index: int | None = None) -> Part:
        """Record that a waiting or active part is now at ``location`` (and ``route_index``).

        A step's own result is better recorded by :meth:`end_step` (same transaction).
        """
        _check_location(location)
        with self._write() as db:
            part = _get_part(db, part_id)
            _require(part, ("waiting", "active"), "be moved")
            new_index = part.route_index if route_index is None else route_index
            return self._update(db, part, self._now(), location=location, route_index=new_index)

    def hold_part(self, part_id: str, reason: str) -> Part:
        """Hold a waiting part for the operator (already held: changes nothing).

        To hold a part because its step went wrong, pass ``hold=`` to :meth:`end_step`.
        """
        with self._write() as db:
            part = _get_part(db, part_id)
            if part.status == "held":
                return part
            if part.status == "active":
                raise UsageError(f"part {part_id} has a step in flight: end it with hold=")
            _require(part, ("waiting",), "be held")
            return self._update(db, part, self._now(), status="held", note=reason)

    def release_part(
        self,
        part_id: str,
        redo_step: bool = False,
        location: str | None = None,
        *,
        emptied: Iterable[str] = (),
    ) -> Part:
        """The operator releases a held part: it waits again at its location (or ``location``).

        The step that got it held (interrupted or failed) then counts as done for
        :meth:`step_done`, so it is not run again, unless ``redo_step``. A part held after
        an interrupted transfer needs ``location``: only the operator knows where it is.
        ``emptied``: the places it may have been in and is not (kept as for
        :meth:`scrap_part`'s ``taken_out_of``, in the same transaction).
        """
        if location is not None:
            _check_location(location)
        with self._write() as db:
            part = _get_part(db, part_id)
            _require(part, ("held",), "be released")
            step = _held_step(db, part_id)
            if step is None and redo_step:
                raise UsageError(f"part {part_id} was held by hand: it has no step to redo")
            if step is not None and step.kind == "transfer" and location is None:
                raise UsageError(
                    f"part {part_id} was held after an interrupted transfer: "
                    f"say where it is now (e.g. {', '.join(LOCATIONS)})"
                )
            if step is not None:
                db.execute(
                    "UPDATE steps SET resolution = ? WHERE id = ?",
                    ("redo" if redo_step else "accepted", step.id),
                )
                self._keep_step(_get_step(db, step.id))
            now = self._now()
            self._emptied(db, emptied, part.id, now)
            return self._update(
                db,
                part,
                now,
                status="waiting",
                location=location or part.location,
                note="",
                held_step=None,
            )

    def scrap_part(self, part_id: str, reason: str, *, taken_out_of: Iterable[str] = ()) -> Part:
        """Scrap a waiting or held part (already scrapped: changes nothing).

        ``taken_out_of``: the places the operator took it out of, kept as emptied
        (:meth:`emptied_places`) in the same transaction: the cell opens their vises before
        it loads them again."""
        with self._write() as db:
            part = _get_part(db, part_id)
            if part.status == "scrapped":
                return part
            _require(part, ("waiting", "held"), "be scrapped")
            now = self._now()
            self._emptied(db, taken_out_of, part.id, now)
            return self._update(db, part, now, status="scrapped", note=reason, held_step=None)

    def _emptied(
        self, db: sqlite3.Connection, places: Iterable[str], part_id: str, now: float
    ) -> None:
        """Inside :meth:`_write`: ``places`` emptied of part ``part_id`` by the operator."""
        for place in places:
            db.execute(
                "INSERT INTO emptied (place, part_id, since) VALUES (?, ?, ?)"
                " ON CONFLICT (place) DO UPDATE SET part_id = excluded.part_id,"
                " since = excluded.since",
                (place, part_id, now),
            )
            self._after_commit(functools.partial(self._views.emptied, place, part_id))

    def emptied_places(self) -> dict[str, str]:
        """``place -> part id`` for each place a scrapped part was taken out of by hand whose
        vise is not known open yet (:meth:`vise_open`)."""
        with self._lock:
            return self._viewed().emptied_places()

    def vise_open(self, place: str) -> None:
        """``place``'s vise is open (or a part is in it again): it is no longer emptied."""
        with self._write() as db:
            db.execute("DELETE FROM emptied WHERE place = ?", (place,))
            self._after_commit(lambda: self._views.emptied(place, None))

    def cancel_parts(self, order_id: str) -> list[Part]:
        """Cancel every part of an order that has not started (one transaction, all or none).

        Refused (UsageError) once any part of the order has had a step: a started order is
        finished, or its parts are scrapped one by one.
        """
        with self._write() as db:
            rows = db.execute("SELECT * FROM parts WHERE order_id = ?", (order_id,)).fetchall()
            parts = [_part(r) for r in rows]
            (steps,) = db.execute(
                "SELECT COUNT(*) FROM steps WHERE part_id IN"
                " (SELECT id FROM parts WHERE order_id = ?)",
                (order_id,),
            ).fetchone()
            started = [p for p in parts if p.status != "waiting" or p.route_index]
            if steps or started:
                raise UsageError(
                    f"order {order_id} has started ({steps} step(s) run): it cannot be "
                    "cancelled; scrap its waiting parts one by one instead"
                )
            now = self._now()
            return [
                self._update(db, p, now, status="cancelled", note="order cancelled") for p in parts
            ]

    def finish_part(self, part_id: str) -> Part:
        """Mark a waiting part done (already done: changes nothing)."""
        with self._write() as db:
            part = _get_part(db, part_id)
            if part.status == "done":
                return part
            _require(part, ("waiting",), "be finished")
            return self._update(db, part, self._now(), status="done", note="")

    # -- steps -------------------------------------------------------------------------------

    def begin_step(self, part_id: str, kind: str, machine: str, program: str) -> Step:
        """Journal a step on a waiting part, before it starts; the part becomes active.

        Returns when the step is on disk: start the machine only after that.
        """
        if kind not in STEP_KINDS:
            raise UsageError(f"unknown step kind {kind!r} (known: {', '.join(STEP_KINDS)})")
        now = self._now()
        with self._write() as db:
            part = _get_part(db, part_id)
            _require(part, ("waiting",), "start a step")
            (earlier,) = db.execute(
                "SELECT COUNT(*) FROM steps WHERE part_id = ? AND kind = ? AND machine = ?"
                " AND program = ? AND route_index = ?",
                (part_id, kind, machine, program, part.route_index),
            ).fetchone()
            cur = db.execute(
                "INSERT INTO steps (part_id, kind, machine, program, route_index, state,"
                " started, attempt) VALUES (?, ?, ?, ?, ?, 'started', ?, ?)",
                (part_id, kind, machine, program, part.route_index, now, earlier + 1),
            )
            self._update(db, part, now, status="active")
            step_id = cur.lastrowid
        assert step_id is not None
        return Step(
            step_id,
            part_id,
            kind,
            machine,
            program,
            "started",
            now,
            None,
            "",
            earlier + 1,
            part.route_index,
        )

    def end_step(
        self,
        step_id: int,
        state: str,
        outcome: str = "",
        *,
        location: str | None = None,
        route_index: int | None = None,
        hold: str | None = None,
    ) -> Step:
        """Journal the end of a step (``finished`` or ``failed``), after it ended.

        In the same transaction the part becomes waiting again, at ``location`` and
        ``route_index`` when given, or held with the reason ``hold``. Ending a step again
        with the same state changes nothing.
        """
        if state not in ("finished", "failed"):
            raise UsageError(f"a step ends finished or failed, not {state!r}")
        if location is not None:
            _check_location(location)
        now = self._now()
        with self._write() as db:
            step = _get_step(db, step_id)
            if step.state == state:
                return step
            if step.state != "started":
                raise UsageError(f"step {step_id} is already {step.state}")
            db.execute(
                "UPDATE steps SET state = ?, ended = ?, outcome = ? WHERE id = ?",
                (state, now, outcome, step_id),
            )
            part = _get_part(db, step.part_id)
            changes: dict[str, Any] = {"status": "waiting"}
            if hold is not None:
                changes.update(status="held", note=hold, held_step=step_id)
            if location is not None:
                changes["location"] = location
            if route_index is not None:
                changes["route_index"] = route_index
            self._update(db, part, now, **changes)
            return self._keep_step(_get_step(db, step_id))

    def open_steps(self) -> list[Step]:
        """Steps started and never ended: while running, those in flight; after a crash,
        what :meth:`recover` will mark interrupted."""
        return [_step(r) for r in self._read("SELECT * FROM steps WHERE state = 'started'")]

    def steps(self, part_id: str | None = None) -> list[Step]:
        """Every step (of ``part_id`` if given), oldest first."""
        if part_id is None:
            return [_step(r) for r in self._read("SELECT * FROM steps ORDER BY id")]
        rows = self._read("SELECT * FROM steps WHERE part_id = ? ORDER BY id", (part_id,))
        return [_step(r) for r in rows]

    def step_done(
        self, part_id: str, kind: str, machine: str, program: str, route_index: int
    ) -> bool:
        """Whether this step needs no running: it finished, or the operator accepted it
        (released its part without ``redo_step`` after it was interrupted or failed)."""
        with self._lock:
            return self._viewed().step_done((part_id, kind, machine, program, route_index))

    def recover(self) -> RecoveryReport:
        """Call once at start, before anything else: settle what a crash left in flight.

        Every open step becomes ``interrupted``; its part is held, with the note
        "needs inspection: machining step ..." for a machining step (the cut may be half
        done: never restarted automatically) or "interrupted transfer: check the gripper
        and both stations" for a transfer (the part may be at either end or in the gripper,
        so its location is unknown). Calling it again finds nothing more to do.
        """
        now = self._now()
        interrupted: list[Step] = []
        held: list[Part] = []
        with self._write() as db:
            rows = db.execute("SELECT * FROM steps WHERE state = 'started' ORDER BY id")
            for step in [_step(r) for r in rows.fetchall()]:
                db.execute(
                    "UPDATE steps SET state = 'interrupted', outcome = ? WHERE id = ?",
                    ("in flight when the controller stopped", step.id),
                )
                interrupted.append(_get_step(db, step.id))
                if step.kind == "machine":
                    reason = INTERRUPTED_MACHINING.format(
                        program=step.program, machine=step.machine
                    )
                else:
                    reason = INTERRUPTED_TRANSFER
                part = _get_part(db, step.part_id)
                if part.status in ("done", "scrapped"):
                    continue
                held.append(
                    self._update(db, part, now, status="held", note=reason, held_step=step.id)
                )
        return RecoveryReport(interrupted, held)

    # -- machines ----------------------------------------------------------------------------

    def set_machine_service(self, name: str, in_service: bool, reason: str = "") -> None:
        """Take a machine out of service (with the reason) or put it back."""
        now = self._now()
        with self._write() as db:
            db.execute(
                "INSERT INTO machines (name, in_service, reason, updated) VALUES (?, ?, ?, ?)"
                " ON CONFLICT (name) DO UPDATE SET in_service = excluded.in_service,"
                " reason = excluded.reason, updated = excluded.updated",
                (name, int(in_service), reason, now),
            )
            # Every change is kept too: the shift report's downtime needs when and why.
            db.execute(
                "INSERT INTO service_log (time, name, in_service, reason) VALUES (?, ?, ?, ?)",
                (now, name, int(in_service), reason),
            )
            self._after_commit(lambda: self._views.machine(name, in_service, reason))

    def machines_out_of_service(self) -> dict[str, str]:
        """``machine name -> reason`` for every machine out of service."""
        with self._lock:
            return self._viewed().out_of_service()

    def service_log(self) -> list[tuple[float, str, bool, str]]:
        """Every change of a machine's service, oldest first: ``(time, name, in_service,
        reason)``; a machine out of service since before the log began shows as going out
        when its row in ``machines`` last changed."""
        rows = self._read("SELECT time, name, in_service, reason FROM service_log ORDER BY id")
        found = [(float(r[0]), str(r[1]), bool(r[2]), str(r[3])) for r in rows]
        logged = {name for _, name, _, _ in found}
        older = self._read("SELECT name, reason, updated FROM machines WHERE in_service = 0")
        found += [(float(r[2]), r[0], False, r[1]) for r in older if r[0] not in logged]
        return sorted(found, key=lambda row: row[0])

    # -- the controller ----------------------------------------------------------------------

    def note_controller(self, event: str, by: str = "", why: str = "") -> None:
        """Record the controller's ``event`` (one of :data:`CONTROLLER_EVENTS`), by whom
        (``token:eve (engineer)``; "" for the controller itself) and why."""
        if event not in CONTROLLER_EVENTS:
            raise UsageError(f"no controller event {event!r}: {', '.join(CONTROLLER_EVENTS)}")
        with self._write() as db:
            db.execute(
                "INSERT INTO controller_log (time, event, by, why) VALUES (?, ?, ?, ?)",
                (self._now(), event, by, why),
            )

    def controller_log(self) -> list[tuple[float, str, str, str]]:
        """Every controller event, oldest first: ``(time, event, by, why)``."""
        rows = self._read("SELECT time, event, by, why FROM controller_log ORDER BY id")
        return [(float(r[0]), str(r[1]), str(r[2]), str(r[3])) for r in rows]

    # -- figures -----------------------------------------------------------------------------

    def busy_time(
        self, machine: str, since: float | None = None, until: float | None = None
    ) -> float:
        """Seconds ``machine`` spent in steps between ``since`` and ``until`` (default: all).

        Steps in flight count up to ``until`` (or now); interrupted steps, whose end is not
        known, do not count.
        """
        end_of_open = until if until is not None else self._now()
        total = 0.0
        rows = self._read(
            "SELECT started, ended, state FROM steps WHERE machine = ?"
            " AND state IN ('started', 'finished', 'failed')",
            (machine,),
        )
        for r in rows:
            start = float(r["started"])
            end = float(r["ended"]) if r["ended"] is not None else end_of_open
            if since is not None:
                start = max(start, since)
            if until is not None:
                end = min(end, until)
            total += max(0.0, end - start)
        return total

    def makespan(self, order_id: str | None = None) -> float | None:
        """Seconds from the first step's start to the last step's end (of ``order_id``'s
        parts if given); None before any step ended."""
        sql = "SELECT MIN(s.started), MAX(s.ended) FROM steps s JOIN parts p ON p.id = s.part_id"
        args: tuple[str, ...] = ()
        if order_id is not None:
            sql += " WHERE p.order_id = ?"
            args = (order_id,)
        (first, last) = self._read(sql, args)[0]
        if first is None or last is None:
            return None
        return float(last) - float(first)


# -- helpers -----------------------------------------------------------------------------------


def _check_location(location: str) -> None:
    if not location or any(c.isspace() for c in location):
        raise UsageError(f"a location is one word, e.g. {', '.join(LOCATIONS)}; not {location!r}")


def _require(part: Part, statuses: tuple[str, ...], action: str) -> None:
    if part.status not in statuses:
        raise UsageError(f"part {part.id} is {part.status}: it cannot {action}")
