"""``cellctl submit|orders|reports|alarm|part`` on a temporary cell directory."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from cellctl.cell.journal import open_journal
from cellctl.mailbox import open_mailbox
from cellctl.service.methods import local_caller
from cellctl.ui.cli import main
from cellctl.ui.common import stop_signals

#: Who a command typed at this computer acts as (no $CELLCTL_TOKEN): ``local:USER``.
LOCAL_USER = local_caller().who

CELL_TOML = """
[parts.wax-robot]
route = ["cnc1", "cnc2"]

[parts.toy-mill]
route = ["cnc1"]
"""


@dataclass(frozen=True)
class AnOrder:
    id: str
    part_type: str
    qty: int


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    directory.mkdir()
    (directory / "cell.toml").write_text(CELL_TOML)
    return directory


def cellctl(cell: Path, *args: str) -> Result:
    # A wide terminal, so rich tables keep each row on one line.
    return CliRunner().invoke(main, ["--cell", str(cell), *args], env={"COLUMNS": "200"})


def test_submit_posts_an_order_once(cell: Path) -> None:
    result = cellctl(cell, "submit", "wax-robot", "--qty", "3", "--priority", "2", "--id", "A17")
    assert result.exit_code == 0, result.output
    assert "order A17 posted: 3 × wax-robot, priority 2" in result.stdout

    # The same order again (a retry): nothing changes, and it says so.
    again = cellctl(cell, "submit", "wax-robot", "--qty", "3", "--priority", "2", "--id", "A17")
    assert again.exit_code == 0
    assert "order A17 was posted before (posted): nothing changed" in again.stdout
    # Another order under that id: refused, saying what the id already stands for.
    other = cellctl(cell, "submit", "wax-robot", "--qty", "5", "--id", "A17")
    assert other.exit_code == 2
    assert (
        "order A17 was posted before as 3 × wax-robot, priority 2 (posted), not 5 × wax-robot, "
        "priority 0: nothing changed (give this order another --id)"
    ) in other.stderr

    with open_mailbox(cell) as mailbox:
        order = mailbox.get_order("A17")
        assert (order.part_type, order.qty, order.priority, order.state) == (
            "wax-robot",
            3,
            2,
            "posted",
        )


def test_submit_refuses_a_part_type_the_cell_does_not_know(cell: Path) -> None:
    result = cellctl(cell, "submit", "teapot")
    assert result.exit_code == 2
    assert "unknown part type 'teapot' (known in cell.toml: toy-mill, wax-robot)" in result.stderr
    assert not (cell / "mailbox.sqlite3").exists()


def test_submit_without_cell_toml_warns_and_posts(tmp_path: Path) -> None:
    open_mailbox(tmp_path / "bare").close()  # a mailbox-only cell: the system level's side
    result = cellctl(tmp_path / "bare", "submit", "anything", "--id", "x1")
    assert result.exit_code == 0, result.output
    assert "warning" in result.stderr and "not checked" in result.stderr
    with open_mailbox(tmp_path / "bare") as mailbox:
        assert mailbox.get_order("x1").part_type == "anything"


def test_submit_refuses_zero_quantity(cell: Path) -> None:
    assert cellctl(cell, "submit", "wax-robot", "--qty", "0").exit_code == 2


def test_orders_lists_by_priority_with_states(cell: Path) -> None:
    assert cellctl(cell, "orders").stdout.startswith("no orders")
    for oid, prio in [("low", "0"), ("high", "5")]:
        assert cellctl(cell, "submit", "toy-mill", "--id", oid, "--priority", prio).exit_code == 0
    with open_mailbox(cell) as mailbox:
        mailbox.set_order_state("low", "accepted")

    due = "2099-12-04T18:00"
    assert cellctl(cell, "submit", "toy-mill", "--id", "due", "--due", due).exit_code == 0

    result = cellctl(cell, "orders")
    assert result.exit_code == 0, result.output
    rows = [line for line in result.stdout.splitlines() if "toy-mill" in line]
    assert "high" in rows[0] and "posted" in rows[0]
    assert "low" in rows[1] and "accepted" in rows[1]
    assert "due" in rows[2] and "2099-12-04 18:00:00" in rows[2] and "LATE" not in rows[2]

    only = cellctl(cell, "orders", "--state", "accepted")
    assert "low" in only.stdout and "high" not in only.stdout


def test_reports_lists_what_the_cell_posted(cell: Path) -> None:
    assert cellctl(cell, "reports").stdout.startswith("no reports")
    with open_mailbox(cell) as mailbox:
        mailbox.post_report("order-accepted", "order A17 accepted", order_id="A17")
        mailbox.post_report("step-started", "cnc1 ROUGH on A17-1", order_id="A17", part_id="A17-1")
    result = cellctl(cell, "reports")
    assert result.exit_code == 0
    assert "order-accepted" in result.stdout and "step-started" in result.stdout
    later = cellctl(cell, "reports", "--since", "1")
    assert "order-accepted" not in later.stdout and "A17-1" in later.stdout


def held_after_crash(cell: Path, kind: str = "machine") -> str:
    """A part held because a step was in flight when the controller died."""
    with open_journal(cell) as journal:
        (part, *_) = journal.create_parts(AnOrder("A17", "wax-robot", 2))
        if kind == "machine":
            journal.move_part(part.id, "cnc1", 0)  # put there by a transfer
            journal.begin_step(part.id, "machine", "cnc1", "ROUGH")
        else:
            journal.begin_step(part.id, "transfer", "robot", "conveyor_to_cnc1")
        journal.recover()
    return part.id


def test_release_a_held_part(cell: Path) -> None:
    part_id = held_after_crash(cell)
    listed = cellctl(cell, "part", "list", "--status", "held")
    assert part_id in listed.stdout and "needs inspection" in listed.stdout
    assert "A17-2" not in listed.stdout

    result = cellctl(cell, "part", "release", part_id)
    assert result.exit_code == 0, result.output
    assert "counts as done" in result.stdout
    with open_journal(cell) as journal:
        assert journal.get_part(part_id).status == "waiting"
        assert journal.step_done(part_id, "machine", "cnc1", "ROUGH", 0)
    with open_mailbox(cell) as mailbox:
        (report,) = mailbox.reports()
        assert (report.kind, report.part_id, report.order_id) == ("part-released", part_id, "A17")
        assert report.data["redo"] is False

    again = cellctl(cell, "part", "release", part_id)
    assert again.exit_code == 2
    assert "is waiting: it cannot be released" in again.stderr


def test_release_with_redo(cell: Path) -> None:
    part_id = held_after_crash(cell)
    result = cellctl(cell, "part", "release", part_id, "--redo")
    assert result.exit_code == 0, result.output
    with open_journal(cell) as journal:
        assert not journal.step_done(part_id, "machine", "cnc1", "ROUGH", 0)


def test_release_after_interrupted_transfer_asks_where_the_part_is(cell: Path) -> None:
    part_id = held_after_crash(cell, kind="transfer")
    refused = cellctl(cell, "part", "release", part_id)
    assert refused.exit_code == 2
    assert "say where it is now" in refused.stderr
    result = cellctl(cell, "part", "release", part_id, "--at", "cnc1")
    assert result.exit_code == 0, result.output
    assert "its interrupted step counts as done" in result.stdout  # it got where it went
    with open_journal(cell) as journal:
        assert journal.get_part(part_id).location == "cnc1"


def test_a_part_released_where_its_transfer_began_is_said_to_be_carried_again(
    cell: Path,
) -> None:
    part_id = held_after_crash(cell, kind="transfer")
    result = cellctl(cell, "part", "release", part_id, "--at", "conveyor")
    assert result.exit_code == 0, result.output
    said = " ".join(result.stdout.split())
    assert (
        f"part {part_id} released at conveyor: the cell takes it up at conveyor, so its "
        "interrupted transfer will run again" in said
    ), said
    with open_journal(cell) as journal:
        part = journal.get_part(part_id)
        assert (part.status, part.location, part.route_index) == ("waiting", "conveyor", 0)
    with open_mailbox(cell) as mailbox:
        (report,) = mailbox.reports()
        assert "its interrupted transfer will run again" in report.text


def test_scrap_a_held_part(cell: Path) -> None:
    part_id = held_after_crash(cell)
    # Held in cnc1's vise: scrapped only once it is said to be out (cnc1 is loaded again).
    refused = cellctl(cell, "part", "scrap", part_id, "--reason", "gouged by the cutter")
    assert refused.exit_code == 2
    assert f"part {part_id} may be in cnc1: take it out" in refused.stderr
    assert f"cellctl part scrap {part_id} --taken-out" in refused.stderr
    with open_journal(cell) as journal:
        assert journal.get_part(part_id).status == "held"
    result = cellctl(
        cell, "part", "scrap", part_id, "--reason", "gouged by the cutter", "--taken-out"
    )
    assert result.exit_code == 0, result.output
    # One line however wide the terminal (rich wraps at its width).
    said = " ".join(result.stdout.split())
    assert "taken out of cnc1, which takes parts again once its vise is open" in said
    with open_journal(cell) as journal:
        part = journal.get_part(part_id)
        assert (part.status, part.note) == ("scrapped", "gouged by the cutter")
    with open_mailbox(cell) as mailbox:
        (report,) = mailbox.reports()
        assert report.kind == "part-scrapped"
        assert report.data["reason"] == "gouged by the cutter"


def test_scrap_after_an_interrupted_transfer_asks_for_its_target_emptied(cell: Path) -> None:
    part_id = held_after_crash(cell, kind="transfer")
    # On the conveyor in the journal, but the arm may have put it in cnc1's vise.
    listed = cellctl(cell, "part", "list", "--json")
    assert json.loads(listed.stdout)[0]["may_be_in"] == ["cnc1"]
    shown = cellctl(cell, "part", "list")
    assert "conveyor or cnc1?" in shown.stdout, shown.stdout
    refused = cellctl(cell, "part", "scrap", part_id)
    assert refused.exit_code == 2
    assert f"part {part_id} may be in cnc1: take it out" in refused.stderr
    result = cellctl(cell, "part", "scrap", part_id, "--taken-out")
    assert result.exit_code == 0, result.output
    with open_journal(cell) as journal:
        assert journal.get_part(part_id).status == "scrapped"


def test_a_waiting_part_on_the_conveyor_is_scrapped_without_asking(cell: Path) -> None:
    with open_journal(cell) as journal:
        (part, *_) = journal.create_parts(AnOrder("A18", "wax-robot", 1))
    result = cellctl(cell, "part", "scrap", part.id)
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == f"part {part.id} scrapped"


def test_part_commands_on_a_cell_that_never_ran(cell: Path) -> None:
    assert cellctl(cell, "part", "list").stdout.startswith("no parts")
    result = cellctl(cell, "part", "release", "A17-1")
    assert result.exit_code == 2
    assert "no journal" in result.stderr


def test_unknown_part(cell: Path) -> None:
    held_after_crash(cell)
    result = cellctl(cell, "part", "scrap", "nope")
    assert result.exit_code == 2
    assert result.stderr.strip() == "error: no part 'nope'"


def test_alarm_list_and_clear_while_the_controller_holds_the_journal(cell: Path) -> None:
    # The controller keeps its journal open; the operator's clear is a fact it reads next poll.
    with open_journal(cell) as controller:
        alarm, _ = controller.raise_alarm("cnc1", "64", "door open")
        listed = cellctl(cell, "alarm", "list")
        assert "door open" in listed.stdout and "active" in listed.stdout
        assert "Priority" in listed.stdout and "medium" in listed.stdout  # as history shows it

        result = cellctl(cell, "alarm", "clear", str(alarm.id))
        assert result.exit_code == 0, result.output
        assert f"alarm {alarm.id} cleared" in result.stdout
        assert controller.active_alarms() == []
        # Cleared by whom the audit names: the local user at the command line.
        assert controller.get_alarm(alarm.id).cleared_by == LOCAL_USER

        assert "no active alarms" in cellctl(cell, "alarm", "list").stdout
        assert "door open" in cellctl(cell, "alarm", "list", "--all").stdout
        again = cellctl(cell, "alarm", "clear", str(alarm.id))
        assert again.exit_code == 0
        assert "already cleared" in again.stdout

    with open_mailbox(cell) as mailbox:
        (report,) = mailbox.reports()
        assert report.kind == "alarm-cleared"
        assert report.data == {"alarm": alarm.id, "machine": "cnc1", "code": "64", "by": LOCAL_USER}

    missing = cellctl(cell, "alarm", "clear", "99")
    assert missing.exit_code == 2
    assert "no alarm 99" in missing.stderr


RUN_CLI = "import sys; from cellctl.ui.cli import main; sys.exit(main())"


def test_reports_follow_prints_new_reports_as_they_come(cell: Path) -> None:
    with open_mailbox(cell) as mailbox:
        mailbox.post_report("order-accepted", "order A17 accepted", order_id="A17")
        follower = subprocess.Popen(
            [sys.executable, "-c", RUN_CLI, "--cell", str(cell), "reports", "--follow"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "COLUMNS": "200"},
        )
        try:
            assert follower.stdout is not None
            assert "order A17 accepted" in follower.stdout.readline()
            mailbox.post_report("order-done", "order A17 done", order_id="A17")
            line = follower.stdout.readline()
            assert "order-done" in line and "order A17 done" in line
        finally:
            follower.terminate()
            follower.communicate(timeout=30)


@pytest.mark.parametrize(
    "start",
    [
        "pass",
        # Ignored: how a script's background job starts; blocked: a parent's mask, kept by exec.
        "signal.signal(signal.SIGINT, signal.SIG_IGN)",
        "signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})",
    ],
    ids=["default", "ignored", "blocked"],
)
def test_reports_follow_stops_on_ctrl_c_however_it_was_started(cell: Path, start: str) -> None:
    with open_mailbox(cell) as mailbox:
        mailbox.post_report("order-accepted", "order A17 accepted", order_id="A17")
    code = f"import signal, sys; {start}; {RUN_CLI}"
    follower = subprocess.Popen(
        [sys.executable, "-c", code, "--cell", str(cell), "reports", "--follow", "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert follower.stdout is not None
        assert "order A17 accepted" in follower.stdout.readline()
        follower.send_signal(signal.SIGINT)
        _, err = follower.communicate(timeout=30)
    finally:
        if follower.poll() is None:
            follower.kill()
            follower.communicate()
    assert (follower.returncode, err.strip()) == (130, "interrupted")


def test_a_stop_on_ctrl_c_leaves_the_signals_as_it_found_them() -> None:
    """In this process, as a command run in process would: SIGINT ignored and blocked before,
    caught while stopping, ignored and blocked again after."""

    async def stopped_by_ctrl_c() -> bool:
        stop = asyncio.Event()
        with stop_signals(stop):
            signal.raise_signal(signal.SIGINT)
            async with asyncio.timeout(10):
                await stop.wait()
        return stop.is_set()

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        assert asyncio.run(stopped_by_ctrl_c())
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        signal.signal(signal.SIGINT, previous)


def test_a_stop_on_ctrl_c_does_not_hand_back_asyncios_own_ctrl_c_handler() -> None:
    """asyncio.run's Ctrl-C handler belongs to that run: the block leaves Python's default."""

    async def handlers_around_a_stop() -> tuple[object, object]:
        found = signal.getsignal(signal.SIGINT)
        with stop_signals(asyncio.Event()):
            pass
        return found, signal.getsignal(signal.SIGINT)

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        found, left = asyncio.run(handlers_around_a_stop())
        assert found is not signal.default_int_handler  # the run's own, set by asyncio.run
        assert left is signal.default_int_handler
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_directory_that_is_no_cell_is_refused_not_shown_empty(tmp_path: Path) -> None:
    """A mistyped --cell: `orders` and `reports` say there is no cell there (as `alarm list`
    does), not "no orders"."""
    for args in (["orders"], ["orders", "--json"], ["reports"]):
        result = cellctl(tmp_path / "celll", *args)
        assert result.exit_code == 2, result.output
        assert "error: no cell at" in result.stderr, result.stderr
        assert "no cell.toml and no mailbox" in result.stderr
    assert not (tmp_path / "celll").exists()  # nothing made there


def test_traffic_without_a_controller_says_whose_traffic_it_is(cell: Path) -> None:
    result = cellctl(cell, "traffic", "cnc1")
    assert result.exit_code == 2
    assert "no controller runs on" in result.stderr and "(`cellctl run`)" in result.stderr
    assert "--trace FILE" in result.stderr
