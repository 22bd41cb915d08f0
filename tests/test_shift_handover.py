"""What a shift hands over: the parts held and the alarms still open at the window's end, in
the shift report's table, --json and CSV; and the CSV's alarm rows name their machine.

The journal is built through the real journal API with a clock the test sets, so that what
was open at the window's end differs from what is open now.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

from cellctl.cell.journal import Journal
from cellctl.cell.shift import shift_report
from cellctl.ui.report_cli import WIDTH, shift_csv, shift_html, shift_lines

from .conftest import SetClock as Clock


@dataclass
class Order:
    id: str
    part_type: str
    qty: int


def _journal(tmp_path: Path) -> Journal:
    """Parts and alarms around a window [1000, 1100] (the test's clock)."""
    clock = Clock(1000.0)
    j = Journal(tmp_path / "journal.sqlite3", clock=clock)
    p1, p2, p3 = j.create_parts(Order("O", "base", 3))
    clock.at = 1010
    first, _ = j.raise_alarm("cnc1", "status", "spindle stalled")
    step = j.begin_step(p1.id, "machine", "cnc1", "rough")
    clock.at = 1020
    j.end_step(step.id, "failed", "stalled", location="cnc1", hold="needs inspection: rough")
    conveyor, _ = j.raise_alarm("plc", "conveyor", "no pallet")
    clock.at = 1030
    j.ack_alarm(first.id, by="token:olga")
    clock.at = 1040
    j.return_to_normal("cnc1", ["status"])  # the spindle turns again: open until cleared
    clock.at = 1050
    j.hold_part(p2.id, "check the surface")
    clock.at = 1060
    j.raise_alarm("cnc2", "link", "no answer")
    clock.at = 1070
    j.clear_alarm(conveyor.id, by="token:olga")
    clock.at = 1080
    j.release_part(p2.id)  # held within the window, released before its end
    clock.at = 1090
    late, _ = j.raise_alarm("cnc2", "status", "door open")
    # After the window: cleared, held, raised: none of it changes what was open at 1100.
    clock.at = 1150
    j.clear_alarm(late.id, by="token:eve")
    j.hold_part(p3.id, "dropped")
    j.raise_alarm("robot", "status", "gripper")
    return j


def test_the_report_says_what_was_held_and_open_at_the_windows_end(tmp_path: Path) -> None:
    journal = _journal(tmp_path)
    report = shift_report(journal, ["robot", "cnc1", "cnc2"], {}, 1000.0, 1100.0).as_dict()

    (held,) = report["held_at_end"]
    assert held["part"] == "O-1" and held["location"] == "cnc1"
    assert held["why"] == "needs inspection: rough" and held["since"] == 1020
    opened = {a["id"]: a for a in report["open_alarms_at_end"]}
    assert [(a["machine"], a["code"]) for a in opened.values()] == [
        ("cnc1", "status"),
        ("cnc2", "link"),
        ("cnc2", "status"),
    ]
    first, link, late = opened.values()
    assert (first["acknowledged"], first["acked_by"]) == (True, "token:olga")
    assert not first["active"]  # returned to normal at 1040
    assert (link["acknowledged"], link["active"]) == (False, True)
    # Cleared (and so acknowledged) only after the window: open, unacknowledged at its end.
    assert (late["acknowledged"], late["active"]) == (False, True)

    lines = shift_lines(report, "a cell")
    assert max(len(x) for x in lines) <= WIDTH
    text = "\n".join(lines)
    assert "at the window's end: 1 part held, 3 alarms open (2 not acknowledged)" in text
    (part,) = [x for x in lines if x.lstrip().startswith("O-1 ")]
    assert "at cnc1" in part and "needs inspection: rough" in part
    # Each alarm: what it is, then where it stood at the window's end.
    (at,) = [i for i, x in enumerate(lines) if x.lstrip().startswith(f"alarm {first['id']} ")]
    assert "cnc1 status (high)" in lines[at] and "spindle stalled" in lines[at]
    assert lines[at + 1].strip() == "returned to normal, acknowledged by token:olga"
    (at,) = [i for i, x in enumerate(lines) if x.lstrip().startswith(f"alarm {link['id']} ")]
    assert lines[at + 1].strip() == "still active, not acknowledged"

    rows = list(csv.reader(io.StringIO(shift_csv(report))))
    assert ["held_at_end", "O-1", "why", "needs inspection: rough", "cnc1"] in rows
    assert ["open_alarm_at_end", str(link["id"]), "acknowledged", "no", "cnc2"] in rows
    assert ["open_alarm_at_end", str(first["id"]), "acked_by", "token:olga", "cnc1"] in rows

    page = shift_html(report, [], "a cell")
    assert "<h2>Handover</h2>" in page and "no answer; still active, not acknowledged" in page

    # At 1200 the window's end sees P3 held and the robot's alarm; P1 still held.
    later = shift_report(journal, ["robot"], {}, 1000.0, 1200.0).as_dict()
    assert [p["part"] for p in later["held_at_end"]] == ["O-1", "O-3"]
    assert [(a["machine"], a["code"]) for a in later["open_alarms_at_end"]] == [
        ("cnc1", "status"),
        ("cnc2", "link"),
        ("robot", "status"),
    ]
    journal.close()


def test_nothing_to_hand_over_is_said_so(tmp_path: Path) -> None:
    journal = _journal(tmp_path)
    report = shift_report(journal, ["cnc1"], {}, 0.0, 900.0).as_dict()
    assert report["held_at_end"] == [] and report["open_alarms_at_end"] == []
    assert "at the window's end: no part held, no alarm open" in shift_lines(report)
    journal.close()


def test_csv_alarm_rows_name_their_machine(tmp_path: Path) -> None:
    journal = _journal(tmp_path)
    report = shift_report(journal, ["cnc1", "cnc2"], {}, 1000.0, 1100.0).as_dict()
    rows = list(csv.reader(io.StringIO(shift_csv(report))))
    assert rows[0] == ["section", "name", "field", "value", "machine"]
    alarms = [r for r in rows if r[0] == "alarms"]
    # status: once on cnc1, once on cnc2; each row says which (the counts add up per cause).
    assert ["alarms", "status", "count", "1", "cnc1"] in alarms
    assert ["alarms", "status", "count", "1", "cnc2"] in alarms
    assert ["alarms", "conveyor", "count", "1", "plc"] in alarms
    assert ["alarms", "status", "priority", "high", "cnc2"] in alarms
    assert all(r[4] for r in alarms), alarms
    # Every machine's and downtime's row names its machine too.
    assert all(r[4] == r[1] for r in rows if r[0] == "machine")
    assert all(r[4] == r[1] for r in rows if r[0] == "downtime")
    journal.close()
