"""An order's due time: kept in the SQLite mailbox (a file from before due times gains it, and
an older cellctl still reads and writes that file), carried on the factory's wire only when
there is one, typed as ``cellctl submit --due WHEN`` as ``cellctl plan --until`` takes it, and
shown by ``cellctl orders`` with whether the order is late. Real files, the real CLI in its
own process."""

from __future__ import annotations

import json
import math
import os
import shutil
import sqlite3
import subprocess
import textwrap
import time
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from cellctl.clock import RealClock
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.errors import UsageError
from cellctl.mailbox import MAILBOX_FILE, SqliteMailbox, open_mailbox
from cellctl.mailbox.wire import OrderMessage, parse_to_cell
from tests.conftest import CELLCTL, released_together

#: The orders, reports and meta tables as cellctl made them before due times.
OLD_SCHEMA = """
CREATE TABLE orders (
    id TEXT PRIMARY KEY, part_type TEXT NOT NULL, qty INTEGER NOT NULL,
    priority INTEGER NOT NULL, state TEXT NOT NULL, created REAL NOT NULL,
    updated REAL NOT NULL, note TEXT NOT NULL DEFAULT ''
);
CREATE TABLE reports (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, kind TEXT NOT NULL,
    order_id TEXT, part_id TEXT, text TEXT NOT NULL, data TEXT NOT NULL DEFAULT '{}'
);
CREATE INDEX orders_by_state ON orders (state);
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
INSERT INTO meta VALUES ('epoch', '0123456789abcdef');
INSERT INTO orders VALUES ('OLD1', 'wax-robot-base', 3, 5, 'accepted', 100.0, 101.0, '');
INSERT INTO orders VALUES ('OLD2', 'wax-robot-base', 1, 0, 'posted', 102.0, 102.0, '');
INSERT INTO reports (time, kind, order_id, text) VALUES (101.0, 'order-accepted', 'OLD1', 'ok');
"""
#: How a cellctl from before due times posts and reads orders: by the columns it names.
OLD_INSERT = (
    "INSERT INTO orders (id, part_type, qty, priority, state, created, updated)"
    " VALUES (?, ?, ?, ?, ?, ?, ?)"
)
OLD_COLUMNS = ("id", "part_type", "qty", "priority", "state", "created", "updated", "note")


def old_mailbox(path: Path) -> Path:
    """A mailbox file as the previous cellctl left it: two orders, a report, its epoch."""
    path.parent.mkdir(parents=True, exist_ok=True)
    db = sqlite3.connect(path)
    db.executescript(OLD_SCHEMA)
    db.commit()
    db.close()
    return path


def columns(path: Path) -> list[str]:
    with sqlite3.connect(path) as db:
        return [row[1] for row in db.execute("PRAGMA table_info(orders)")]


# -- the mailbox ----------------------------------------------------------------------------------


def test_a_due_time_is_kept_and_seen_by_another_connection(tmp_path: Path) -> None:
    path = tmp_path / MAILBOX_FILE
    with SqliteMailbox(path) as cli, SqliteMailbox(path) as controller:
        assert controller.orders() == [] and controller.due_times() == {}  # views read
        cli.post_order("p", 2, order_id="D", due=1_800_000_000)
        cli.post_order("p", 1, order_id="N")
        # The other connection's views are read again (another connection committed).
        assert controller.due_times() == {"D": 1_800_000_000.0}
        assert [o.id for o in controller.orders()] == ["D", "N"]
        # Posted again (a retry), another due time or none: the first order, its due kept.
        again, new = controller.post_order("p", 2, order_id="D", due=1_900_000_000)
        assert not new and again == cli.get_order("D")
        controller.set_order_state("D", "accepted")
        assert cli.due_times() == controller.due_times() == {"D": 1_800_000_000.0}
    with open_mailbox(tmp_path) as reopened:
        assert reopened.due_times() == {"D": 1_800_000_000.0}
        assert reopened.get_order("D").state == "accepted"


@pytest.mark.parametrize("due", [math.nan, math.inf, -1.0, 1e12, True, "18:00"])
def test_a_due_time_that_is_no_time_is_refused_and_nothing_is_posted(
    tmp_path: Path, due: Any
) -> None:
    with SqliteMailbox(tmp_path / MAILBOX_FILE) as mailbox:
        with pytest.raises(UsageError, match="due time"):
            mailbox.post_order("p", order_id="X", due=due)
        assert mailbox.orders() == [] and mailbox.due_times() == {}


def test_a_mailbox_from_before_due_times_gains_the_column_and_loses_nothing(
    tmp_path: Path,
) -> None:
    path = old_mailbox(tmp_path / "cell" / MAILBOX_FILE)
    with open_mailbox(tmp_path / "cell") as mailbox:
        assert columns(path).count("due") == 1
        assert mailbox.epoch == "0123456789abcdef"  # the same mailbox: the factory's marks hold
        assert [(o.id, o.state, o.qty, o.priority) for o in mailbox.orders()] == [
            ("OLD1", "accepted", 3, 5),
            ("OLD2", "posted", 1, 0),
        ]
        assert mailbox.due_times() == {}  # none had one
        assert [r.text for r in mailbox.reports()] == ["ok"]
        mailbox.post_order("wax-robot-base", 2, order_id="NEW", due=1_800_000_000)
        # The previous cellctl, on the file now (the CLI of the controller's older install):
        # it writes and reads by the columns it names, as before.
        with sqlite3.connect(path) as old:
            old.execute(OLD_INSERT, ("OLDER", "wax-robot-base", 1, 0, "posted", 200.0, 200.0))
            old.row_factory = sqlite3.Row
            rows = old.execute("SELECT rowid AS rank, * FROM orders ORDER BY rank").fetchall()
            assert [tuple(r[c] for c in OLD_COLUMNS)[:2] for r in rows] == [
                ("OLD1", "wax-robot-base"),
                ("OLD2", "wax-robot-base"),
                ("NEW", "wax-robot-base"),
                ("OLDER", "wax-robot-base"),
            ]
        assert mailbox.get_order("OLDER").state == "posted"
        assert mailbox.due_times() == {"NEW": 1_800_000_000.0}
    with open_mailbox(tmp_path / "cell") as again:  # opened again: the column is not added twice
        assert sorted(o.id for o in again.orders()) == ["NEW", "OLD1", "OLD2", "OLDER"]
    assert columns(path).count("due") == 1


OPENER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from cellctl.mailbox import open_mailbox

    name, cell = sys.argv[1], Path(sys.argv[2])
    print("ready", flush=True)
    sys.stdin.readline()  # open together with the other process
    with open_mailbox(cell) as mb:
        for i in range(20):
            mb.post_order("p", order_id=f"{name}-{i}", due=1_800_000_000 + i)
    print("posted", flush=True)
    """
)


def test_two_processes_opening_an_old_mailbox_at_once_add_the_column_once(
    tmp_path: Path,
) -> None:
    path = old_mailbox(tmp_path / MAILBOX_FILE)
    argvs = [["a", str(tmp_path)], ["b", str(tmp_path)]]
    for code, out, err in released_together(OPENER, argvs, timeout=60):
        assert (code, out.strip()) == (0, "posted"), err
    assert columns(path).count("due") == 1
    with open_mailbox(tmp_path) as mailbox:
        assert len(mailbox.orders()) == 2 + 40  # the old ones, and every one posted, once
        assert mailbox.due_times()["b-19"] == 1_800_000_019.0


# -- the factory's wire ---------------------------------------------------------------------------


def test_the_wire_carries_a_due_time_only_when_there_is_one() -> None:
    before = {"v": 1, "id": "F1", "part_type": "wax-robot-base", "qty": 2, "priority": 0}
    # A factory of before (no due): the order as it was, due none.
    taken = parse_to_cell(json.dumps(before).encode())
    assert isinstance(taken, OrderMessage) and taken.due is None
    # Without a due time the payload is the one an older cell takes: no field it does not know.
    plain = json.loads(OrderMessage(id="F1", part_type="wax-robot-base", qty=2).model_dump_json())
    assert set(plain) == {*before, "expires"}
    due = OrderMessage(id="F1", part_type="wax-robot-base", qty=2, due=1_800_000_000.0)
    assert json.loads(due.model_dump_json())["due"] == 1_800_000_000.0
    assert parse_to_cell(due.model_dump_json().encode()) == due


# -- cellctl submit --due, cellctl orders ---------------------------------------------------------


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    """A copy of the example cell: its cell.toml and programs, no mailbox yet."""
    directory = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    return directory


def cellctl(cell: Path, *args: str, expect: int = 0) -> subprocess.CompletedProcess[str]:
    """``cellctl --cell CELL ARGS`` in its own process (a wide terminal: one row a line)."""
    done = subprocess.run(
        [*CELLCTL, "--cell", str(cell), *args],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "COLUMNS": "250"},
    )
    assert done.returncode == expect, (done.stdout, done.stderr)
    return done


def local(stamp: float) -> datetime:
    return datetime.fromtimestamp(stamp)


def test_submit_due_takes_the_forms_plan_until_takes(cell: Path) -> None:
    before = time.time()
    cellctl(cell, "submit", "wax-robot-base", "--qty", "40", "--due", "FRI 18:00", "--id", "FRI")
    cellctl(cell, "submit", "wax-robot-base", "--due", "18:00", "--id", "SIX")
    said = cellctl(cell, "submit", "wax-robot-base", "--due", "2099-12-04T18:00", "--id", "ISO")
    assert said.stdout.strip() == (
        "order ISO posted: 1 × wax-robot-base, priority 0, due Fri 2099-12-04 18:00:00"
    )
    cellctl(cell, "submit", "wax-robot-base", "--id", "NONE")
    after = time.time()
    with open_mailbox(cell) as mailbox:
        due = mailbox.due_times()
    # FRI 18:00: the next Friday 18:00 on the cell's clock; 18:00: the next 18:00 (never past).
    friday = local(due["FRI"])
    assert (friday.weekday(), friday.hour, friday.minute, friday.second) == (4, 18, 0, 0)
    assert before < due["FRI"] <= after + 7 * 86400
    six = local(due["SIX"])
    assert (six.hour, six.minute) == (18, 0) and before < due["SIX"] <= after + 86400
    assert due["ISO"] == datetime(2099, 12, 4, 18, 0).timestamp()
    assert "NONE" not in due


@pytest.mark.parametrize(
    ("due", "words"),
    [
        ("FRYDAY 18:00", "--due: 'FRYDAY' is not a day (MON TUE WED THU FRI SAT SUN)"),
        ("25:00", "--due: time '25:00': hours 0-23, minutes 0-59"),
        ("next week", "--due: time 'next week': write HH:MM, DAY HH:MM (FRI 18:00) or a date"),
        ("9999-12-31T00:00", "--due: an order's due time must be unix seconds from 0 to"),
        ("x" * 80, "--due: a due time is at most 60 characters"),
    ],
)
def test_a_malformed_due_is_refused_in_words_before_anything_is_written(
    cell: Path, due: str, words: str
) -> None:
    refused = cellctl(cell, "submit", "wax-robot-base", "--due", due, expect=2)
    assert words in refused.stderr and refused.stdout == ""
    assert not (cell / MAILBOX_FILE).exists()


def test_a_due_time_already_past_is_taken_and_the_order_is_late(cell: Path) -> None:
    past = (datetime.now() - timedelta(days=2)).replace(second=0, microsecond=0)
    said = cellctl(cell, "submit", "wax-robot-base", "--due", past.isoformat(), "--id", "BACK")
    assert said.stdout.strip().endswith("(already past: the order is late)"), said.stdout
    [listed] = json.loads(cellctl(cell, "orders", "--json").stdout)
    assert (listed["id"], listed["due"], listed["late"]) == ("BACK", past.timestamp(), True)
    # The same order again is the same order; another due time under its id is refused.
    again = cellctl(cell, "submit", "wax-robot-base", "--due", past.isoformat(), "--id", "BACK")
    assert again.stdout.strip() == "order BACK was posted before (posted): nothing changed"
    other = cellctl(cell, "submit", "wax-robot-base", "--id", "BACK", expect=2)
    assert "order BACK was posted before as 1 × wax-robot-base, priority 0, due " in other.stderr
    assert "not 1 × wax-robot-base, priority 0: nothing changed" in other.stderr


class Then(RealClock):
    """The mailbox's clock at a time the test sets: when an order's state changed."""

    def __init__(self) -> None:
        super().__init__()
        self.at = 0.0

    def now(self) -> float:
        return self.at


def test_orders_say_each_due_time_and_whether_the_order_is_late(cell: Path) -> None:
    now = time.time()
    hour = 3600.0
    clock = Then()
    # (id, due, state, when it got there): late once done after its due time, or not done
    # past it (open or failed); a cancelled order is owed nothing; no due time, never late.
    cases = [
        ("done-late", now - 2 * hour, "done", now - hour),
        ("done-in-time", now - hour, "done", now - 2 * hour),
        ("open-past", now - hour, "in-progress", now - 2 * hour),
        ("open-ahead", now + hour, "accepted", now - hour),
        ("failed-past", now - hour, "failed", now - 2 * hour),
        ("cancelled-past", now - hour, "cancelled", now - 2 * hour),
        ("no-due", None, "accepted", now - hour),
    ]
    with SqliteMailbox(cell / MAILBOX_FILE, clock=clock) as mailbox:
        for oid, due, state, at in cases:
            clock.at = now - 3 * hour
            mailbox.post_order("wax-robot-base", order_id=oid, due=due)
            clock.at = at
            path = {"done": ["accepted", "done"], "in-progress": ["accepted", "in-progress"]}
            for step in path.get(state, [state]):
                mailbox.set_order_state(oid, step)
    listed = {o["id"]: o for o in json.loads(cellctl(cell, "orders", "--json").stdout)}
    assert {oid: (listed[oid]["due"], listed[oid]["late"]) for oid, *_ in cases} == {
        "done-late": (now - 2 * hour, True),
        "done-in-time": (now - hour, False),
        "open-past": (now - hour, True),
        "open-ahead": (now + hour, False),
        "failed-past": (now - hour, True),
        "cancelled-past": (now - hour, False),
        "no-due": (None, False),
    }
    table = cellctl(cell, "orders").stdout
    rows = {line.split("│")[1].strip(): line for line in table.splitlines() if "│" in line}
    shown = local(now - 2 * hour).strftime("%Y-%m-%d %H:%M:%S")
    assert f"{shown} LATE" in rows["done-late"]
    assert "LATE" not in rows["done-in-time"] and "LATE" not in rows["cancelled-past"]
    assert "LATE" in rows["open-past"] and "LATE" in rows["failed-past"]
    assert "Due" in table
