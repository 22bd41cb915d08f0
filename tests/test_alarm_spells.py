"""An alarm's active spells, and the shift report's down time made of them.

An alarm whose condition returns to normal and comes back while it is open stays one alarm
(ISA-18.2): the shift report counts the spells it was active, not the span from raised to its
last return. Journals driven through their own API on a file, with a clock the test sets; an
older journal (no ``alarm_spells`` table) reporting as before; and an emulated cell whose link
goes away twice with a gap.
"""

from __future__ import annotations

import sqlite3
import tempfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.cell.causes import ESTOP
from cellctl.cell.journal import Journal, Spell
from cellctl.cell.shift import shift_report
from cellctl.clock import current_clock
from cellctl.service.access import LocalCell
from cellctl.service.methods import Dispatcher
from cellctl.testing.rig import CellRig

from .conftest import SetClock as Clock


def down(journal: Journal, machine: str, start: float, end: float) -> float:
    """``machine``'s down time over ``[start, end]`` as the shift report gives it."""
    return shift_report(journal, [machine], {}, start, end).machines[0].down_s


def by_reason(journal: Journal, start: float, end: float) -> dict[tuple[str, str], float]:
    report = shift_report(journal, [], {}, start, end)
    return {(d["machine"], d["reason"]): d["seconds"] for d in report.downtime_by_reason}


def test_a_condition_that_came_back_counts_its_spells_not_the_span(tmp_path: Path) -> None:
    """The tester's case: the link went at :02, back at :06, gone again at :30, back at :33:
    7 s down, not the 31 s from the first loss to the last return."""
    clock = Clock()
    with Journal(tmp_path / "journal.sqlite3", clock=clock) as journal:
        alarm, new = journal.raise_alarm("robot", "link", "robot not answering")
        assert new
        clock.at = 1004.0
        journal.return_to_normal("robot", ["link"])
        clock.at = 1028.0
        again = journal.reactivate(alarm.id)  # what the controller does: the same alarm
        assert again.id == alarm.id and again.returned is None
        clock.at = 1031.0
        journal.return_to_normal("robot", ["link"])
        clock.at = 1040.0
        cleared = journal.clear_alarm(alarm.id)
        assert cleared.returned == 1031.0  # the alarm's row keeps its last return only
        assert journal.alarm_spells()[alarm.id] == [Spell(1000.0, 1004.0), Spell(1028.0, 1031.0)]
        assert down(journal, "robot", 900.0, 1100.0) == 4.0 + 3.0
        assert by_reason(journal, 900.0, 1100.0) == {("robot", "alarm: link"): 7.0}
        # A window that cuts the spells counts what is inside it.
        assert down(journal, "robot", 1002.0, 1029.0) == 2.0 + 1.0
        assert down(journal, "robot", 1005.0, 1027.0) == 0.0  # the gap: normal, not down


def test_raised_again_after_its_return_is_a_spell_too(tmp_path: Path) -> None:
    """``raise_alarm`` with the same machine, code and text after a return to normal makes
    the same alarm active again: a new spell, as :meth:`Journal.reactivate` does."""
    clock = Clock()
    with Journal(tmp_path / "journal.sqlite3", clock=clock) as journal:
        alarm, _ = journal.raise_alarm("plc", "link", "PLC not answering")
        clock.at = 1004.0
        journal.return_to_normal("plc", ["link"])
        clock.at = 1028.0
        again, new = journal.raise_alarm("plc", "link", "PLC not answering")
        assert (again.id, new) == (alarm.id, False)
        clock.at = 1031.0
        journal.raise_alarm("plc", "link", "PLC not answering")  # seen again: nothing new
        journal.return_to_normal("plc", ["link"])
        # The PLC not answering stops the whole cell: down for every machine too.
        assert by_reason(journal, 900.0, 1100.0) == {
            ("plc", "alarm: link"): 7.0,
            ("cell", "alarm: plc link"): 7.0,
        }


def test_a_chattering_alarm_counts_only_its_active_spells(tmp_path: Path) -> None:
    """Active 0.5 s, normal 1.5 s, ten times over 20 s (``--fault robot:noise``): 5 s down."""
    clock = Clock()
    with Journal(tmp_path / "journal.sqlite3", clock=clock) as journal:
        alarm, _ = journal.raise_alarm("robot", "status", "status record garbled")
        for n in range(10):
            clock.at = 1000.0 + 2 * n
            journal.reactivate(alarm.id)  # the first: still active, changes nothing
            clock.at += 0.5
            journal.return_to_normal("robot", ["status"])
        clock.at = 1030.0
        journal.clear_alarm(alarm.id)
        spells = journal.alarm_spells()[alarm.id]
        assert len(spells) == 10
        assert all(s.ended is not None and s.ended - s.began == 0.5 for s in spells)
        assert down(journal, "robot", 990.0, 1100.0) == pytest.approx(5.0)  # not the 18.5 s span


def test_an_alarm_active_at_the_reports_end_counts_to_it(tmp_path: Path) -> None:
    clock = Clock()
    with Journal(tmp_path / "journal.sqlite3", clock=clock) as journal:
        alarm, _ = journal.raise_alarm("cnc1", "link", "mill not answering")
        clock.at = 1010.0
        journal.return_to_normal("cnc1", ["link"])
        clock.at = 1050.0
        journal.reactivate(alarm.id)
        assert journal.alarm_spells()[alarm.id] == [Spell(1000.0, 1010.0), Spell(1050.0, None)]
        assert down(journal, "cnc1", 900.0, 1100.0) == 10.0 + 50.0
        assert down(journal, "cnc1", 900.0, 1070.0) == 10.0 + 20.0
        assert down(journal, "cnc1", 1060.0, 1100.0) == 40.0
        # Cleared while active: the clear ends its spell; nothing after counts.
        clock.at = 1120.0
        journal.clear_alarm(alarm.id)
        assert journal.alarm_spells()[alarm.id][-1] == Spell(1050.0, 1120.0)
        assert down(journal, "cnc1", 900.0, 1200.0) == 10.0 + 70.0


def test_overlapping_alarms_of_one_machine_count_once(tmp_path: Path) -> None:
    """cnc1's link (active 1000-1010 and 1020-1030) and its status (1005-1025) overlap, and
    the cell's estop (1026-1028) too: cnc1 was down 1000-1030, 30 s. By reason each counts
    apart, and two alarms of one code at once (two link texts) count once."""
    clock = Clock()
    with Journal(tmp_path / "journal.sqlite3", clock=clock) as journal:
        link, _ = journal.raise_alarm("cnc1", "link", "mill not answering")
        clock.at = 1005.0
        journal.raise_alarm("cnc1", "status", "mill lost readiness")
        clock.at = 1008.0
        closed, _ = journal.raise_alarm("cnc1", "link", "link closed by the other end")
        clock.at = 1010.0
        journal.return_to_normal("cnc1", ["link"])  # both link alarms
        clock.at = 1020.0
        journal.reactivate(link.id)
        clock.at = 1025.0
        journal.return_to_normal("cnc1", ["status"])
        clock.at = 1026.0
        estop, _ = journal.raise_alarm("cell", "estop", "emergency stop")
        clock.at = 1028.0
        journal.clear_alarm(estop.id)
        clock.at = 1030.0
        journal.return_to_normal("cnc1", ["link"])
        assert down(journal, "cnc1", 900.0, 1100.0) == 30.0
        assert by_reason(journal, 900.0, 1100.0) == {
            ("cnc1", "alarm: link"): 10.0 + 10.0,  # 1000-1010 once, though two alarms
            ("cnc1", "alarm: status"): 20.0,
            ("cell", "alarm: estop"): 2.0,
        }
        assert journal.alarm_spells()[closed.id] == [Spell(1008.0, 1010.0)]


# -- an older journal: no alarm_spells table ------------------------------------------------

#: The journal's tables as they were before spells were kept (journalrows.SCHEMA, with the
#: alarm columns every journal of that time had after opening).
OLD_SCHEMA = """
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
    cleared_by TEXT NOT NULL DEFAULT '',
    priority TEXT NOT NULL DEFAULT 'medium',
    acked REAL,
    acked_by TEXT NOT NULL DEFAULT '',
    returned REAL,
    shelved_until REAL,
    shelved_by TEXT NOT NULL DEFAULT ''
);
CREATE INDEX IF NOT EXISTS alarms_by_state ON alarms (state);
CREATE TABLE IF NOT EXISTS machines (
    name TEXT PRIMARY KEY,
    in_service INTEGER NOT NULL,
    reason TEXT NOT NULL,
    updated REAL NOT NULL
);
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
"""


def old_journal(path: Path) -> None:
    """A journal as the cellctl before spells wrote it: cnc1's link alarm returned at 1020
    and was cleared at 1030; its status alarm cleared at 1050 with no return; the robot's
    link alarm returned at 1070 and is open still; the PLC's link alarm active still."""
    db = sqlite3.connect(path)
    db.executescript(OLD_SCHEMA)
    db.executemany(
        "INSERT INTO alarms (raised, machine, code, text, state, cleared, returned, priority)"
        " VALUES (?, ?, ?, ?, ?, ?, ?, 'high')",
        [
            (1010.0, "cnc1", "link", "mill not answering", "cleared", 1030.0, 1020.0),
            (1040.0, "cnc1", "status", "mill lost readiness", "cleared", 1050.0, None),
            (1060.0, "robot", "link", "robot not answering", "active", None, 1070.0),
            (1080.0, "plc", "link", "PLC not answering", "active", None, None),
        ],
    )
    db.commit()
    db.close()


def test_an_older_journal_reports_as_before(tmp_path: Path) -> None:
    path = tmp_path / "journal.sqlite3"
    old_journal(path)
    clock = Clock()
    with Journal(path, clock=clock) as journal:
        # Each old alarm is one spell: raised to returned, else cleared, else open.
        assert list(journal.alarm_spells().values()) == [
            [Spell(1010.0, 1020.0)],
            [Spell(1040.0, 1050.0)],
            [Spell(1060.0, 1070.0)],
            [Spell(1080.0, None)],
        ]
        report = shift_report(journal, ["cnc1", "robot"], {}, 1000.0, 1100.0)
        # The PLC's link alarm, open to the window's end, is down for every machine too.
        assert [m.down_s for m in report.machines] == [10.0 + 10.0 + 20.0, 10.0 + 20.0]
        assert by_reason(journal, 1000.0, 1100.0) == {
            ("cnc1", "alarm: link"): 10.0,
            ("cnc1", "alarm: status"): 10.0,
            ("robot", "alarm: link"): 10.0,
            ("plc", "alarm: link"): 20.0,  # open: to the window's end
            ("cell", "alarm: plc link"): 20.0,
        }
        # The robot's old alarm comes back and goes again under this cellctl: its first
        # spell (from its columns) is kept before the new one. The PLC's is cleared.
        clock.at = 1090.0
        journal.reactivate(3)
        clock.at = 1095.0
        journal.return_to_normal("robot", ["link"])
        journal.clear_alarm(4)
        assert journal.alarm_spells()[3] == [Spell(1060.0, 1070.0), Spell(1090.0, 1095.0)]
        assert journal.alarm_spells()[4] == [Spell(1080.0, 1095.0)]
        # Its own spells, and the PLC's link alarm (1080-1095: its own 1090-1095 inside it).
        assert down(journal, "robot", 1000.0, 1100.0) == 10.0 + 15.0
    # The table was made on open; the alarms left alone have no rows (their columns say it).
    db = sqlite3.connect(path)
    rows = db.execute("SELECT alarm_id, began, ended FROM alarm_spells ORDER BY rowid").fetchall()
    db.close()
    assert rows == [(3, 1060.0, 1070.0), (3, 1090.0, 1095.0), (4, 1080.0, 1095.0)]


# -- any sequence ---------------------------------------------------------------------------

EVENTS = st.lists(
    st.tuples(st.sampled_from(["raise", "rtn", "reactivate", "clear"]), st.floats(0.25, 20.0)),
    max_size=25,
)


@settings(max_examples=60, deadline=None)
@given(EVENTS, st.floats(0.0, 200.0), st.floats(1.0, 200.0))
def test_down_time_is_the_union_of_the_spells_of_any_sequence(
    events: list[tuple[str, float]], offset: float, length: float
) -> None:
    """A model of one machine's ``link`` alarms (active from a raise or a reactivation, to a
    return or a clear) against the report, over any window."""
    clock = Clock()
    with tempfile.TemporaryDirectory() as tmp, Journal(Path(tmp) / "j.sqlite3", clock=clock) as j:
        active: list[tuple[float, float | None]] = []  # the model's spells, in order
        current: int | None = None
        for event, gap in events:
            clock.at += gap
            now = clock.at
            is_active = bool(active) and active[-1][1] is None
            if event == "raise":
                a, new = j.raise_alarm("cnc1", "link", "mill not answering")
                if new or not is_active:
                    active.append((now, None))
                current = a.id
            elif current is None:
                continue
            elif event == "rtn":
                j.return_to_normal("cnc1", ["link"])
                if is_active:
                    active[-1] = (active[-1][0], now)
            elif event == "reactivate":
                before = j.get_alarm(current)
                j.reactivate(current)
                if before.state == "active" and not is_active:
                    active.append((now, None))
            else:
                j.clear_alarm(current)
                if is_active:
                    active[-1] = (active[-1][0], now)
                current = None
        start = 1000.0 + offset
        end = start + length
        expected = sum(
            max(0.0, min(end if t1 is None else t1, end) - max(t0, start)) for t0, t1 in active
        )
        assert down(j, "cnc1", start, end) == pytest.approx(expected, abs=2e-3)


# -- an emulated cell ------------------------------------------------------------------------


@pytest.mark.parametrize("machine", ["robot", "plc"])
@pytest.mark.virtual
async def test_a_link_lost_twice_is_down_twice_not_between(tmp_path: Path, machine: str) -> None:
    """The link of an idle cell's robot (or PLC) goes silent, comes back, stays well a while
    with its alarm left open, goes silent again and comes back: one alarm, active twice. The
    report's down time is its two outages, from the journal's times, less than the span."""
    fault = f"{machine}:silent"
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        start = current_clock().now()
        rig.switch_on(fault)
        (alarm,) = await rig.wait_for(lambda: rig.alarms(machine, "link"), "the link alarm")
        await rig.switch_off(fault)

        def returned() -> float | None:
            return rig.journal.get_alarm(alarm.id).returned

        first_return = await rig.wait_for(returned, "the alarm returned to normal")
        # The link well for a while: nothing new in the journal for 5 s.
        await rig.wait_quiet(span=5.0, what="the link well")
        second_loss = current_clock().now()  # the alarm becomes active again after this
        rig.switch_on(fault)
        await rig.wait_for(lambda: returned() is None, "the same alarm active again")
        seen_active = current_clock().now()  # ... and before this
        await rig.switch_off(fault)
        await rig.wait_for(returned, "the alarm returned to normal again")
        await rig.wait_quiet(span=1.0, what="the link well again")
        await rig.stop_controller()
        end = current_clock().now()
        last = rig.journal.get_alarm(alarm.id)
        assert last.returned is not None and last.state == "active", last
        assert [a.id for a in rig.journal.alarms() if a.machine == machine] == [alarm.id]

        found = await Dispatcher(LocalCell(rig.directory, {})).call(
            "report.shift", {"since": start, "until": end}
        )
        reasons = {(d["machine"], d["reason"]): d["seconds"] for d in found["downtime_by_reason"]}
        counted = reasons[(machine, "alarm: link")]
        span = last.returned - alarm.raised
        first = first_return - alarm.raised
        assert first > 0 and second_loss > first_return
        # Both outages, and nothing of the time between them, well under the span.
        assert first + (last.returned - seen_active) - 1e-3 <= counted
        assert counted <= first + (last.returned - second_loss) + 1e-3
        assert counted < span - 4.0
        if machine == "robot":  # the robot is one of the report's machines
            (robot,) = [m for m in found["machines"] if m["machine"] == "robot"]
            assert robot["down_s"] == pytest.approx(counted, abs=1e-3)


def test_the_plcs_emergency_stop_is_down_time_for_every_machine(tmp_path: Path) -> None:
    """The PLC's E-stop input stops the whole cell: its alarm counts as down for each machine
    (as the cell's own stop does), and for the PLC; another PLC alarm (an interlock not made)
    only for the PLC."""
    clock = Clock()
    with Journal(tmp_path / "journal.sqlite3", clock=clock) as journal:
        journal.raise_alarm(ESTOP.machine, ESTOP.code, ESTOP.text)
        clock.at = 1030.0
        journal.return_to_normal(ESTOP.machine, [ESTOP.code])
        journal.raise_alarm("plc", "interlock", "vise of CNC 1 not closed within 5 s")
        clock.at = 1035.0
        journal.return_to_normal("plc", ["interlock"])
        for machine in ("robot", "cnc1", "cnc2"):
            assert down(journal, machine, 900.0, 1100.0) == 30.0, machine
        assert down(journal, "plc", 900.0, 1100.0) == 35.0
        reasons = by_reason(journal, 900.0, 1100.0)
        assert reasons[("cell", "alarm: plc estop")] == 30.0
        assert reasons[("plc", "alarm: estop")] == 30.0
