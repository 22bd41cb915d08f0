"""The journal's and the mailbox's in-memory views answer what the file answers.

(The stores here mostly say ``durable=False``: what is compared is what the views and the
file answer, not what survives a crash; tests/test_journal.py kills writers.)

The controller reads parts, done steps, alarms, machines and orders every round from memory;
the CLI (another connection, often another process) writes to the same files. Whatever either
side does, in any order, a read through the controller's store equals the same read done
with plain SQL on the file.
"""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.cell.journal import Alarm, Journal, Part, open_journal
from cellctl.cell.sqlitedb import SqliteStore
from cellctl.clock import RealClock
from cellctl.errors import UsageError
from cellctl.mailbox import SqliteMailbox
from cellctl.mailbox.base import Order
from tests.test_journal import AnOrder


class Clock(RealClock):
    """Each reading a little later, and often the same as the one before (ties happen)."""

    def __init__(self) -> None:
        super().__init__()
        self.at = 100.0

    def now(self) -> float:
        self.at += 0.5
        return self.at // 1


# -- the file's own answers, by plain SQL ---------------------------------------------------------


_OPEN: dict[Path, sqlite3.Connection] = {}


def _sql(path: Path, query: str, args: tuple[object, ...] = ()) -> list[sqlite3.Row]:
    """A plain query on the file, through a connection of the test's own (kept open while
    it compares one store with the file: see :func:`_same_as_file`)."""
    if path in _OPEN:
        return _OPEN[path].execute(query, args).fetchall()
    with closing(sqlite3.connect(path)) as db:
        db.row_factory = sqlite3.Row
        return db.execute(query, args).fetchall()


def _parts_in_file(path: Path, where: str = "1", args: tuple[object, ...] = ()) -> list[Part]:
    rows = _sql(
        path,
        "SELECT id, order_id, part_type, seq_in_order, route_index, location, status, updated,"
        f" note FROM parts WHERE {where} ORDER BY rowid",
        args,
    )
    return [Part(*r) for r in rows]


def _alarms_in_file(path: Path, where: str = "1") -> list[Alarm]:
    rows = _sql(
        path,
        "SELECT id, raised, machine, code, text, state, cleared, cleared_by, priority, acked,"
        f" acked_by, returned, shelved_until, shelved_by FROM alarms WHERE {where} ORDER BY id",
    )
    return [Alarm(*r) for r in rows]


def _same_as_file(journal: Journal) -> None:
    with closing(sqlite3.connect(journal.path)) as db:
        db.row_factory = sqlite3.Row
        _OPEN[journal.path] = db
        try:
            _compare(journal)
        finally:
            del _OPEN[journal.path]


def _compare(journal: Journal) -> None:
    path = journal.path
    assert journal.parts() == _parts_in_file(path)
    for statuses in (["waiting"], ["waiting", "active", "held"], ["done", "scrapped"], []):
        marks = ",".join("?" * len(statuses)) or "NULL"
        assert journal.parts(statuses=statuses) == _parts_in_file(
            path, f"status IN ({marks})", tuple(statuses)
        )
    for (order_id,) in _sql(path, "SELECT DISTINCT order_id FROM parts"):
        assert journal.parts(order_id=order_id) == _parts_in_file(path, "order_id = ?", (order_id,))
        assert journal.parts(statuses=["held"], order_id=order_id) == _parts_in_file(
            path, "order_id = ? AND status = 'held'", (order_id,)
        )
    for p in _parts_in_file(path):
        assert journal.get_part(p.id) == p
    for s in _sql(path, "SELECT * FROM steps"):
        key = (s["part_id"], s["kind"], s["machine"], s["program"], s["route_index"])
        done = _sql(
            path,
            "SELECT 1 FROM steps WHERE part_id = ? AND kind = ? AND machine = ? AND program = ?"
            " AND route_index = ? AND (state = 'finished' OR resolution = 'accepted')",
            key,
        )
        assert journal.step_done(*key) == bool(done)
    assert journal.alarms() == _alarms_in_file(path)
    assert journal.active_alarms() == _alarms_in_file(path, "state = 'active'")
    for a in _alarms_in_file(path):
        assert journal.get_alarm(a.id) == a
    out = _sql(path, "SELECT name, reason FROM machines WHERE in_service = 0 ORDER BY name")
    assert journal.machines_out_of_service() == {r[0]: r[1] for r in out}


# -- operations, by the controller or by the operator's CLI ---------------------------------------

MACHINES = ("robot", "cnc1", "cnc2")
OPS = (
    "order",
    "begin",
    "finish",
    "fail",
    "hold",
    "release",
    "redo",
    "scrap",
    "done",
    "cancel",
    "alarm",
    "return",
    "ack",
    "clear",
    "out",
    "in",
    "recover",
)
#: Parts' lives are the most of what happens: drawn more often.
LIKELY = (*OPS, "order", "begin", "begin", "begin", "finish", "finish", "fail")


def _apply(journal: Journal, op: str, n: int) -> None:
    """One operation on the n-th part / alarm / machine that there is (wrapping round): a
    part the operation suits, most of the time."""
    suits = {"begin": ["waiting"], "hold": ["waiting"], "release": ["held"], "redo": ["held"]}
    parts = journal.parts(statuses=suits.get(op)) if n % 5 else journal.parts()
    part = parts[n % len(parts)] if parts else None
    alarms = journal.alarms()
    alarm = alarms[n % len(alarms)] if alarms else None
    machine = MACHINES[n % len(MACHINES)]
    open_steps = journal.open_steps()
    step = open_steps[n % len(open_steps)] if open_steps else None
    try:
        if op == "order":
            journal.create_parts(AnOrder(f"O{n % 4}", "bracket", 1 + n % 3))
        elif op == "begin" and part:
            journal.begin_step(part.id, "machine" if n % 2 else "transfer", machine, f"P{n % 2}")
        elif op in ("finish", "fail") and step:
            state = "finished" if op == "finish" else "failed"
            hold = "needs a look" if op == "fail" and n % 2 else None
            index = journal.get_part(step.part_id).route_index + 1
            journal.end_step(step.id, state, route_index=index, hold=hold)
        elif op == "hold" and part:
            journal.hold_part(part.id, "held by hand")
        elif op in ("release", "redo") and part:
            journal.release_part(part.id, redo_step=op == "redo", location=machine)
        elif op == "scrap" and part:
            journal.scrap_part(part.id, "scrapped")
        elif op == "done" and part:
            journal.finish_part(part.id)
        elif op == "cancel" and part:
            journal.cancel_parts(part.order_id)
        elif op == "alarm":
            journal.raise_alarm(machine, "link", f"fault {n % 3}")
        elif op == "return":
            journal.return_to_normal(machine, ["link"])
        elif op == "ack" and alarm:
            journal.ack_alarm(alarm.id)
        elif op == "clear" and alarm:
            journal.clear_alarm(alarm.id)
        elif op in ("out", "in"):
            journal.set_machine_service(machine, op == "in", f"reason {n}")
        elif op == "recover":
            journal.recover()
    except UsageError:
        pass  # refused: changes nothing, which the comparison checks too


@settings(max_examples=30, deadline=None)
@given(
    st.lists(
        st.tuples(st.sampled_from(LIKELY), st.integers(0, 20), st.booleans()),
        min_size=1,
        max_size=30,
    )
)
def test_the_controllers_reads_equal_the_files_whoever_writes(
    ops: list[tuple[str, int, bool]],
) -> None:
    with tempfile.TemporaryDirectory() as directory:
        clock = Clock()
        with (
            open_journal(Path(directory), clock=clock, durable=False) as controller,
            open_journal(Path(directory), clock=clock, durable=False) as cli,
        ):
            controller.create_parts(AnOrder("first", "bracket", 2))
            _same_as_file(controller)
            for op, n, by_cli in ops:
                _apply(cli if by_cli else controller, op, n)
                _same_as_file(controller)
                _same_as_file(cli)


def test_every_write_of_the_store_shows_at_once_in_its_own_reads(tmp_path: Path) -> None:
    """A part's whole life, alarms and service, all by the controller's own journal: no other
    connection commits, so nothing but its own writes keeps its views right."""
    with open_journal(tmp_path, clock=Clock(), durable=False) as j:
        a, b, c = j.create_parts(AnOrder("A", "bracket", 3))
        _same_as_file(j)
        step = j.begin_step(a.id, "transfer", "robot", "C-1")
        _same_as_file(j)
        j.end_step(step.id, "finished", location="cnc1")
        _same_as_file(j)
        step = j.begin_step(a.id, "machine", "cnc1", "ROUGH")
        j.end_step(step.id, "failed", "stalled", hold="needs inspection")
        _same_as_file(j)
        j.release_part(a.id)  # accepted: the failed cut counts as done
        assert j.step_done(a.id, "machine", "cnc1", "ROUGH", 0)
        _same_as_file(j)
        j.begin_step(b.id, "transfer", "robot", "C-2")
        j.recover()
        _same_as_file(j)
        j.release_part(b.id, location="cnc2")
        j.scrap_part(b.id, "dropped")
        j.finish_part(c.id)
        _same_as_file(j)
        j.create_parts(AnOrder("B", "bracket", 1))
        j.cancel_parts("B")
        j.hold_part(a.id, "by hand")
        _same_as_file(j)
        alarm, _ = j.raise_alarm("cnc1", "link", "no answer")
        j.ack_alarm(alarm.id)
        j.shelve_alarm(alarm.id, 60)
        j.return_to_normal("cnc1", ["link"])
        _same_as_file(j)
        j.reactivate(alarm.id)
        j.clear_alarm(alarm.id)
        j.set_machine_service("cnc2", False, "tooling")
        _same_as_file(j)
        j.set_machine_service("cnc2", True)
        _same_as_file(j)


def test_a_commit_elsewhere_is_seen_on_the_next_read(tmp_path: Path) -> None:
    with open_journal(tmp_path) as controller, open_journal(tmp_path) as cli:
        (part,) = controller.create_parts(AnOrder("A", "bracket", 1))
        assert controller.parts(statuses=["waiting"]) == [part]
        cli.hold_part(part.id, "operator looks at it")
        assert controller.parts(statuses=["waiting"]) == []
        assert controller.get_part(part.id).note == "operator looks at it"
        alarm, _ = controller.raise_alarm("cnc1", "link", "no answer")
        cli.clear_alarm(alarm.id, by="ann")
        assert controller.active_alarms() == []
        assert controller.get_alarm(alarm.id).cleared_by == "ann"


def test_a_commit_by_another_process_is_seen_on_the_next_read(tmp_path: Path) -> None:
    """The operator's CLI is another process: its commit reaches the controller's views."""
    with open_journal(tmp_path) as controller:
        (part,) = controller.create_parts(AnOrder("A", "bracket", 1))
        assert controller.parts(statuses=["waiting"]) == [part]
        script = (
            "import sys; from pathlib import Path; from cellctl.cell.journal import open_journal\n"
            "with open_journal(Path(sys.argv[1])) as j:\n"
            "    j.scrap_part('A-1', 'dropped by the operator')\n"
            "    j.set_machine_service('cnc2', False, 'operator: tooling')\n"
        )
        done = subprocess.run(
            [sys.executable, "-c", script, str(tmp_path)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 0, done.stderr
        assert controller.parts(statuses=["waiting"]) == []
        assert controller.get_part("A-1").note == "dropped by the operator"
        assert controller.machines_out_of_service() == {"cnc2": "operator: tooling"}
        _same_as_file(controller)


class Notes(SqliteStore):
    """A store with one in-memory view, to see what a failed write does to it."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, "CREATE TABLE IF NOT EXISTS notes (text TEXT NOT NULL)")
        self.kept: list[str] = []

    def _load_views(self, db: sqlite3.Connection) -> None:
        self.kept = [r["text"] for r in db.execute("SELECT text FROM notes ORDER BY rowid")]

    def add(self, *texts: str, fail: bool = False) -> None:
        with self._write() as db:
            for text in texts:
                db.execute("INSERT INTO notes (text) VALUES (?)", (text,))
                self._after_commit(lambda text=text: self.kept.append(text))  # type: ignore[misc]
            if fail:
                raise UsageError("refused half-way")

    def notes(self) -> list[str]:
        with self._lock:
            self._views_current()
            return list(self.kept)


def test_a_write_that_rolls_back_leaves_the_view_as_the_file(tmp_path: Path) -> None:
    with Notes(tmp_path / "notes.sqlite3") as notes:
        notes.add("first")
        assert notes.notes() == ["first"]
        with pytest.raises(UsageError, match="half-way"):
            notes.add("second", "third", fail=True)
        assert notes.notes() == ["first"]
        rows = _sql(notes.path, "SELECT text FROM notes")
        assert [r[0] for r in rows] == ["first"]
        before = notes.version
        notes.add("fourth")
        assert notes.version != before
        assert notes.notes() == ["first", "fourth"]


# -- the mailbox's orders -------------------------------------------------------------------------


@pytest.fixture
def two_mailboxes(tmp_path: Path) -> Iterator[tuple[SqliteMailbox, SqliteMailbox]]:
    clock = Clock()
    path = tmp_path / "mailbox.sqlite3"
    with SqliteMailbox(path, clock=clock) as a, SqliteMailbox(path, clock=clock) as b:
        yield a, b


def _orders_in_file(path: Path, where: str = "1", args: tuple[object, ...] = ()) -> list[Order]:
    rows = _sql(
        path,
        "SELECT id, part_type, qty, priority, state, created, updated, note FROM orders"
        f" WHERE {where} ORDER BY priority DESC, created ASC, rowid ASC",
        args,
    )
    return [Order(*r) for r in rows]


MAILBOX_OPS = ("post", "accept", "progress", "done", "cancel", "note")


@settings(max_examples=25, deadline=None)
@given(
    st.lists(
        st.tuples(st.sampled_from(MAILBOX_OPS), st.integers(0, 9), st.booleans()),
        min_size=1,
        max_size=25,
    )
)
def test_the_controllers_orders_equal_the_files_whoever_writes(
    ops: list[tuple[str, int, bool]],
) -> None:
    with tempfile.TemporaryDirectory() as directory:
        clock = Clock()
        path = Path(directory) / "mailbox.sqlite3"
        with (
            SqliteMailbox(path, clock=clock, durable=False) as controller,
            SqliteMailbox(path, clock=clock, durable=False) as cli,
        ):
            for op, n, by_cli in ops:
                box = cli if by_cli else controller
                orders = box.orders()
                order = orders[n % len(orders)] if orders else None
                try:
                    if op == "post":
                        box.post_order("bracket", 1 + n % 3, priority=n % 2, order_id=f"O{n}")
                    elif order is not None:
                        state = {
                            "accept": "accepted",
                            "progress": "in-progress",
                            "done": "done",
                            "cancel": "cancelled",
                        }.get(op, order.state)
                        box.set_order_state(order.id, state, f"note {n}" if op == "note" else "")
                except UsageError:
                    pass  # an illegal transition: refused, changes nothing
                for states in (None, ["posted"], ["accepted", "in-progress", "held"], []):
                    if states is None:
                        want = _orders_in_file(path)
                    else:
                        marks = ",".join("?" * len(states)) or "NULL"
                        want = _orders_in_file(path, f"state IN ({marks})", tuple(states))
                    assert controller.orders(states) == want
                for o in _orders_in_file(path):
                    assert controller.get_order(o.id) == o


def test_an_order_posted_elsewhere_is_seen_at_once(
    two_mailboxes: tuple[SqliteMailbox, SqliteMailbox],
) -> None:
    controller, cli = two_mailboxes
    assert controller.pending_orders() == []
    before = controller.version
    order, new = cli.post_order("bracket", 2, order_id="W1")
    assert new
    assert controller.version != before
    assert controller.pending_orders() == [order]
    controller.set_order_state("W1", "accepted")
    assert [o.state for o in cli.orders()] == ["accepted"]
    assert controller.pending_orders() == []


def test_only_a_throwaway_copy_skips_waiting_for_the_disk(tmp_path: Path) -> None:
    """The controller's journal and mailbox sync every commit (a kill -9 or a power cut loses
    nothing that returned); a plan's copy says ``durable=False`` and is still the same file
    for every reader."""
    with open_journal(tmp_path) as journal, SqliteMailbox(tmp_path / "mailbox.sqlite3") as mb:
        for store in (journal, mb):
            assert store._conn.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
    copy = tmp_path / "plan"
    with open_journal(copy, durable=False) as journal:
        assert journal._conn.execute("PRAGMA synchronous").fetchone()[0] == 0  # OFF
        journal.create_parts(AnOrder("P", "bracket", 2))
        with open_journal(copy) as reader:
            assert [p.id for p in reader.parts()] == ["P-1", "P-2"]


def test_reads_of_an_unchanged_journal_run_no_query(tmp_path: Path) -> None:
    """What the controller asks every round costs one version probe, however many parts the
    journal holds; after another connection commits, the views are read once, then not."""
    # What is tested is reads: the writes need not wait for the disk.
    with (
        open_journal(tmp_path, durable=False) as controller,
        open_journal(tmp_path, durable=False) as cli,
    ):
        for n in range(30):
            controller.create_parts(AnOrder(f"A{n}", "bracket", 5))
        for p in controller.parts()[:140]:
            controller.finish_part(p.id)
        ran: list[str] = []
        controller._conn.set_trace_callback(ran.append)

        def a_round() -> None:
            controller.parts(statuses=["waiting", "active", "held"])
            controller.parts(order_id="A29")
            controller.active_alarms()
            controller.machines_out_of_service()
            controller.step_done("A29-1", "machine", "cnc1", "ROUGH", 0)

        for _ in range(3):
            a_round()
        assert ran and set(ran) == {"PRAGMA data_version"}
        cli.hold_part("A29-5", "operator looks at it")
        ran.clear()
        a_round()
        a_round()
        assert any(q.startswith("SELECT") for q in ran)
        assert ran.count("SELECT rowid AS rank, * FROM parts ORDER BY rowid") == 1
        assert [p.id for p in controller.parts(statuses=["held"])] == ["A29-5"]
