"""Alarm states after ISA-18.2 in the journal: priority from the cause, acknowledged apart
from cleared, returned to normal when the condition goes away, shelving with a time limit,
the history filtered, and an older journal's alarms table brought up to date on open."""

from __future__ import annotations

import sqlite3
import tempfile
from pathlib import Path

import click
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.cell.causes import ALARM_PRIORITY, PRIORITIES, priority_of
from cellctl.cell.journal import MAX_SHELVE, Alarm, Journal
from cellctl.errors import UsageError
from cellctl.ui.orders_cli import _seconds, _since

from .conftest import SetClock as Clock


def test_priorities_come_from_the_cause(tmp_path: Path) -> None:
    assert set(ALARM_PRIORITY.values()) <= set(PRIORITIES)
    with Journal(tmp_path / "j.sqlite3") as journal:
        estop, _ = journal.raise_alarm("plc", "estop", "emergency stop: the cell is stopped")
        late, _ = journal.raise_alarm("plc", "conveyor", "no pallet within 30 s")
        step, _ = journal.raise_alarm("cnc1", "machining", "ROUGH1 failed")
    assert (estop.priority, late.priority, step.priority) == ("high", "low", "medium")
    assert priority_of("status") == "high" and priority_of("link") == "high"


def test_ack_is_not_clear_and_rtn_is_not_either(tmp_path: Path) -> None:
    clock = Clock()
    with Journal(tmp_path / "j.sqlite3", clock=clock) as journal:
        a, new = journal.raise_alarm("robot", "link", "robot not answering")
        assert new and a.unacked(clock.at) and a.returned is None
        clock.at += 5
        acked = journal.ack_alarm(a.id, by="ann")
        assert (acked.acked, acked.acked_by, acked.state) == (1005.0, "ann", "active")
        assert not acked.unacked(clock.at)
        assert journal.ack_alarm(a.id, by="bob").acked_by == "ann"  # again: unchanged
        clock.at += 5
        [back] = journal.return_to_normal("robot", ["link", "status"])
        assert back.returned == 1010.0 and back.state == "active"  # open until cleared
        assert journal.return_to_normal("robot", ["link"]) == []  # nothing more to mark
        # The condition comes back: active and unacknowledged again, the same alarm.
        again, new = journal.raise_alarm("robot", "link", "robot not answering")
        assert not new and again.id == a.id and again.returned is None
        assert again.unacked(clock.at)
        cleared = journal.clear_alarm(a.id, by="bob")
        assert cleared.state == "cleared" and cleared.acked_by == "bob"  # clear acks too
        assert journal.active_alarms() == []


def test_shelving_hides_an_alarm_until_the_time_runs_out(tmp_path: Path) -> None:
    clock = Clock()
    with Journal(tmp_path / "j.sqlite3", clock=clock) as journal:
        a, _ = journal.raise_alarm("cnc1", "link", "mill not answering")
        shelved = journal.shelve_alarm(a.id, 1800, by="ann")
        assert shelved.shelved_until == 2800.0 and not shelved.unacked(clock.at)
        clock.at = 2801.0
        assert journal.get_alarm(a.id).unacked(clock.at)  # back once the time is past
        for bad in (0, -1, MAX_SHELVE + 1, float("nan")):
            with pytest.raises(UsageError, match="8 h"):
                journal.shelve_alarm(a.id, bad)
        journal.clear_alarm(a.id)
        with pytest.raises(UsageError, match="cleared"):
            journal.shelve_alarm(a.id, 60)
        with pytest.raises(UsageError, match="no alarm 99"):
            journal.ack_alarm(99)


def test_history_filters(tmp_path: Path) -> None:
    clock = Clock()
    with Journal(tmp_path / "j.sqlite3", clock=clock) as journal:
        journal.raise_alarm("plc", "estop", "emergency stop")
        clock.at = 2000.0
        late, _ = journal.raise_alarm("plc", "conveyor", "no pallet")
        journal.clear_alarm(late.id)
        cut, _ = journal.raise_alarm("cnc1", "machining", "ROUGH1 failed")
        assert [a.id for a in journal.alarm_history()] == [1, 2, 3]
        assert [a.id for a in journal.alarm_history(since=1500)] == [2, 3]
        assert [a.id for a in journal.alarm_history(machine="plc")] == [1, 2]
        assert [a.id for a in journal.alarm_history(priority="low")] == [2]
        assert [a.id for a in journal.alarm_history(machine="plc", since=1500)] == [2]
        assert [a.id for a in journal.alarm_history(limit=1)] == [cut.id]
        with pytest.raises(UsageError, match="one of high, medium, low"):
            journal.alarm_history(priority="urgent")


def test_an_older_journal_gets_the_alarm_columns(tmp_path: Path) -> None:
    path = tmp_path / "j.sqlite3"
    db = sqlite3.connect(path)
    db.executescript(
        "CREATE TABLE alarms (id INTEGER PRIMARY KEY AUTOINCREMENT, raised REAL NOT NULL,"
        " machine TEXT NOT NULL, code TEXT NOT NULL, text TEXT NOT NULL, state TEXT NOT NULL,"
        " cleared REAL, cleared_by TEXT NOT NULL DEFAULT '');"
        "INSERT INTO alarms (raised, machine, code, text, state)"
        " VALUES (5, 'plc', 'estop', 'emergency stop', 'active');"
    )
    db.commit()
    db.close()
    with Journal(path) as journal:
        [old] = journal.active_alarms()
        assert (old.priority, old.acked, old.returned, old.shelved_until) == (
            "high",
            None,
            None,
            None,
        )
        assert journal.ack_alarm(old.id).acked is not None
    with Journal(path) as journal:  # opening again adds nothing twice
        assert journal.get_alarm(1).acked is not None


# -- any sequence of operator actions and conditions ---------------------------------------

ACTIONS = st.lists(
    st.tuples(
        st.sampled_from(["raise", "ack", "rtn", "clear", "shelve", "unshelve", "tick"]),
        st.integers(1, 3),  # which alarm (by its raise order)
        st.floats(1, MAX_SHELVE),
    ),
    max_size=30,
)


@settings(max_examples=60, deadline=None)
@given(ACTIONS)
def test_any_sequence_keeps_the_states_consistent(actions: list[tuple[str, int, float]]) -> None:
    """A model of one machine's alarms (code ``link``, texts by number) against the journal:
    acked only by ack or clear, never un-cleared, returned only while open, unacked again
    only when its condition comes back, unshelved only while shelved."""
    clock = Clock()
    with tempfile.TemporaryDirectory() as tmp, Journal(Path(tmp) / "j.sqlite3", clock=clock) as j:
        ids: dict[int, int] = {}
        for action, n, seconds in actions:
            clock.at += 1
            alarm_id = ids.get(n)
            before = j.get_alarm(alarm_id) if alarm_id is not None else None
            if action == "raise":
                a, new = j.raise_alarm("cnc1", "link", f"fault {n}")
                assert new == (before is None or before.state == "cleared")
                ids[n] = a.id
                assert a.state == "active" and a.returned is None
                if before is not None and not new and before.returned is None:
                    assert a.acked == before.acked  # a second sighting changes nothing
            elif before is None:
                continue
            elif action == "ack":
                a = j.ack_alarm(before.id)
                assert a.acked is not None or before.state == "cleared"
            elif action == "rtn":
                marked = j.return_to_normal("cnc1", ["link"])
                a = j.get_alarm(before.id)
                if before.state == "active":
                    assert a.returned is not None
                else:
                    assert a.returned == before.returned
                    assert before.id not in [m.id for m in marked]
            elif action == "clear":
                a = j.clear_alarm(before.id)
                assert a.state == "cleared" and a.acked is not None
            elif action == "shelve":
                if before.state == "cleared":
                    with pytest.raises(UsageError):
                        j.shelve_alarm(before.id, seconds)
                    continue
                a = j.shelve_alarm(before.id, seconds)
                assert not a.unacked(clock.at)
            elif action == "unshelve":
                if before.state == "cleared" or not before.shelved(clock.at):
                    with pytest.raises(UsageError):
                        j.unshelve_alarm(before.id)
                    assert j.get_alarm(before.id) == before  # refused: nothing changed
                    continue
                a = j.unshelve_alarm(before.id)
                assert a.shelved_until is None and a.acked == before.acked
            else:
                clock.at += seconds
                a = j.get_alarm(before.id)
            check(a, before, clock.at)


def check(a: Alarm, before: Alarm | None, now: float) -> None:
    if before is not None and before.state == "cleared" and a.id == before.id:
        assert a == before  # a cleared alarm never changes again
    if a.state == "cleared":
        assert a.acked is not None and a.cleared is not None and not a.unacked(now)
    if a.acked is None and a.state == "active":
        assert a.unacked(now) == (not a.shelved(now))


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=30))
def test_a_shelving_time_is_seconds_or_a_clear_refusal(text: str) -> None:
    """``alarm shelve --for`` and ``history --since`` take anything typed: a positive number
    of seconds, or click's usage error naming the option -- never another exception."""
    for parse, option in ((lambda t: _seconds(t, "--for"), "--for"), (_since, "--since")):
        try:
            value = parse(text)
        except click.BadParameter as e:
            assert e.param_hint == option
        else:
            assert value == value and (option == "--since" or value > 0)  # not NaN


def test_shelving_times_read_as_an_operator_writes_them() -> None:
    assert [_seconds(t, "--for") for t in ("30m", "2h", "1h30m", "90s", "45")] == [
        1800,
        7200,
        5400,
        90,
        45,
    ]
