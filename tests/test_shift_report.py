"""The shift report: OEE after ISO 22400, parts, alarms and downtime, from the journal.

Exact figures from a hand-made journal (a clock the test sets), and the same report from a
real run of a small batch on the emulated cell, through the control API and the CLI.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.cell.config import load_cell
from cellctl.cell.journal import Journal
from cellctl.cell.shift import ideal_times, shift_report
from cellctl.clock import current_clock
from cellctl.mailbox import open_mailbox
from cellctl.service.access import LocalCell
from cellctl.service.methods import Dispatcher
from cellctl.testing.rig import CellRig
from cellctl.ui.cli import main
from cellctl.ui.report_cli import WIDTH, shift_csv, shift_html, shift_lines

from .conftest import SetClock as Clock


@dataclass
class Order:
    id: str
    part_type: str
    qty: int


def test_figures_of_a_hand_made_journal(tmp_path: Path) -> None:
    clock = Clock()
    journal = Journal(tmp_path / "journal.sqlite3", clock=clock)
    a, b, c = journal.create_parts(Order("O", "base", 3))
    # The mill cuts A from 1010 to 1040 (ideal 24 s), B from 1050 to 1070 (ideal 24 s: it ran
    # slow), and fails C at 1090 (started 1080); C is then scrapped.
    for part, t0, t1, state in ((a, 1010, 1040, "finished"), (b, 1050, 1070, "finished")):
        clock.at = t0
        step = journal.begin_step(part.id, "machine", "cnc1", "rough")
        clock.at = t1
        journal.end_step(step.id, state, route_index=1)
    clock.at = 1080
    step = journal.begin_step(c.id, "machine", "cnc1", "rough")
    clock.at = 1090
    journal.end_step(step.id, "failed", "stalled", hold="needs inspection")
    journal.scrap_part(c.id, "broken tool")
    journal.finish_part(a.id)
    # An alarm on cnc1 from 1090 to 1100 (returned to normal at 1100, cleared at 1105), and
    # the operator takes cnc1 out from 1095 to 1120: 30 s down in all (the union).
    clock.at = 1090
    alarm, _ = journal.raise_alarm("cnc1", "status", "spindle stalled")
    clock.at = 1095
    journal.set_machine_service("cnc1", False, "tool change")
    clock.at = 1100
    journal.return_to_normal("cnc1", ["status"])
    clock.at = 1105
    journal.clear_alarm(alarm.id)
    clock.at = 1120
    journal.set_machine_service("cnc1", True, "back")
    clock.at = 1130
    journal.raise_alarm("plc", "conveyor", "no pallet")

    report = shift_report(journal, ["cnc1"], {"cnc1/rough": 24.0}, 1000.0, 1200.0)
    m = report.machines[0]
    assert m.planned_s == 200.0
    assert m.production_s == 30 + 20 + 10  # every step's time, the failed one's too
    assert m.availability == pytest.approx(60 / 200)
    assert m.ideal_s == 48.0  # finished steps only
    assert m.performance == pytest.approx(48 / 60)
    assert (m.steps_ended, m.steps_good) == (3, 2)
    # Quality counts parts: A finished, C scrapped (B, cut well, is not finished yet).
    assert (m.parts_ended, m.parts_good) == (2, 1)
    assert m.quality == 0.5
    assert m.oee == pytest.approx(round(0.3 * 0.8 * 0.5, 4))
    assert m.down_s == 30.0
    assert (report.parts_good, report.parts_held, report.parts_scrapped) == (1, 0, 1)
    causes = {x["code"]: x for x in report.alarms_by_cause}
    assert causes["status"] == {"code": "status", "priority": "high", "count": 1,
                                "machines": ["cnc1"], "by_machine": {"cnc1": 1}}  # fmt: skip
    assert causes["conveyor"]["priority"] == "low"
    downs = {(d["machine"], d["reason"]): d["seconds"] for d in report.downtime_by_reason}
    assert downs[("cnc1", "alarm: status")] == 10.0
    assert downs[("cnc1", "out of service: tool change")] == 25.0
    assert downs[("plc", "alarm: conveyor")] == 70.0  # open to the window's end
    # A window that cuts the steps: only their time inside it counts.
    half = shift_report(journal, ["cnc1"], {"cnc1/rough": 24.0}, 1020.0, 1060.0).machines[0]
    assert half.production_s == 20 + 10
    assert half.steps_ended == 1
    # Windows before any down time: nothing down (never negative); one after: only what is
    # still down (the PLC's alarm, never returned to normal).
    for window in ((0.0, 500.0), (1000.0, 1085.0)):
        quiet = shift_report(journal, ["cnc1", "plc"], {}, *window)
        assert [m.down_s for m in quiet.machines] == [0.0, 0.0], window
        assert quiet.downtime_by_reason == []
    later = shift_report(journal, ["cnc1", "plc"], {}, 5000.0, 6000.0)
    assert [m.down_s for m in later.machines] == [0.0, 1000.0]
    journal.close()


def test_the_report_fits_80_columns_and_saves_csv_and_html(tmp_path: Path) -> None:
    clock = Clock()
    journal = Journal(tmp_path / "journal.sqlite3", clock=clock)
    (part,) = journal.create_parts(Order("O", "base", 1))
    step = journal.begin_step(part.id, "machine", "a-mill-with-a-long-name", "rough")
    clock.at = 1100
    journal.end_step(step.id, "finished", route_index=1)
    journal.raise_alarm("a-mill-with-a-long-name", "a-long-cause-of-its-own" * 3, "x" * 300)
    report = shift_report(journal, ["a-mill-with-a-long-name"], {}, 900.0, 1200.0).as_dict()
    lines = shift_lines(report, "a cell")
    assert max(len(x) for x in lines) <= WIDTH
    assert any(x.startswith("a-mill-wi") and "100.0 %" in x for x in lines)  # performance
    rows = list(csv.reader(io.StringIO(shift_csv(report))))
    assert rows[0] == ["section", "name", "field", "value", "machine"]
    mill = "a-mill-with-a-long-name"
    assert ["machine", mill, "availability", str(round(100 / 300, 4)), mill] in rows
    page = shift_html(report, [{**_step_dict(step.id, part.id), "part_type": "base"}], "a cell")
    assert page.count("<svg") == 1 and "<rect x=" in page
    assert "OEE" in page and "a cell" in page
    journal.close()


def _step_dict(step_id: int, part_id: str) -> dict[str, object]:
    return {
        "id": step_id,
        "part_id": part_id,
        "kind": "machine",
        "machine": "a-mill-with-a-long-name",
        "program": "rough",
        "state": "finished",
        "started": 1000.0,
        "ended": 1100.0,
        "outcome": "",
        "attempt": 1,
    }


@pytest.mark.virtual
async def test_the_report_of_a_real_batch(tmp_path: Path) -> None:
    async with CellRig(tmp_path) as rig:
        rig.post("wax-robot-base", 2, "A")
        await rig.start_controller()
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        await rig.stop_controller()
        steps = rig.journal.steps()
        start = min(s.started for s in steps)
        end = current_clock().now()  # after the parts were marked done (the cell's clock)
        dispatcher = Dispatcher(LocalCell(tmp_path, {}))
        found = await dispatcher.call("report.shift", {"since": start, "until": end})
        config = load_cell(tmp_path)
        assert found["time_scale"] == rig.cell.time_scale
        assert found["parts_good"] == 2 and found["parts_scrapped"] == 0
        figures = {m["machine"]: m for m in found["machines"]}
        assert set(figures) == {"robot", "cnc1", "cnc2"}
        ideal = ideal_times(config)
        for name, m in figures.items():
            mine = [s for s in steps if s.machine == name]
            busy = sum((s.ended or end) - s.started for s in mine)
            assert m["steps_ended"] == len(mine) > 0
            assert m["production_s"] == pytest.approx(busy, abs=1e-3)
            assert m["availability"] == pytest.approx(busy / (end - start), abs=1e-4)
            assert m["quality"] == 1.0
            assert m["ideal_s"] == pytest.approx(
                sum(ideal[f"{name}/{s.program}"] for s in mine), abs=1e-3
            )
            # No run beats the machines' own models (the bound's promise).
            assert 0 < m["performance"] <= 1.0
        # The CLI prints it, saves CSV and HTML with the Gantt chart.
        csv_file, html_file = tmp_path / "shift.csv", tmp_path / "shift.html"
        result = await rig.cli("report", "shift", "--csv", str(csv_file), "--html", str(html_file))
        assert result.exit_code == 0, result.output
        assert "parts good 2, held 0, scrapped 0" in result.output
        # The report fits 80 columns; "saved PATH" lines are as long as their paths.
        report = [x for x in result.output.splitlines() if not x.startswith("saved ")]
        assert all(len(line) <= WIDTH for line in report), result.output
        assert f"saved {csv_file}" in result.output.splitlines()
        assert "section,name,field,value" in csv_file.read_text()
        assert html_file.read_text().count("<rect x=") >= len(steps)
        result = await rig.cli("report", "shift", "--json")
        assert json.loads(result.output)["parts_good"] == 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--from", "2026-11-25T10:00", "--to", "2026-11-25T09:00"], "ends before it starts"),
        (["--from", "2026-01-01", "--to", "2026-03-01"], "at most 7 days"),
        (["--from", "yesterday"], "say a date/time"),
    ],
)
def test_a_bad_window_is_refused_with_its_reason(
    tmp_path: Path, args: list[str], message: str
) -> None:
    open_mailbox(tmp_path).close()  # a cell, as the system level sees one
    result = CliRunner().invoke(main, ["--cell", str(tmp_path), "report", "shift", *args])
    assert result.exit_code == 2
    assert message in result.output + (result.stderr or "")


def test_a_good_step_of_a_part_scrapped_later_is_not_good(tmp_path: Path) -> None:
    clock = Clock()
    journal = Journal(tmp_path / "journal.sqlite3", clock=clock)
    a, b = journal.create_parts(Order("O", "base", 2))
    for part in (a, b):
        step = journal.begin_step(part.id, "machine", "cnc1", "rough")
        clock.at += 10
        journal.end_step(step.id, "finished", route_index=1)
    # B's next step, on cnc2, fails; B is held, then scrapped: cnc1 cut it for nothing.
    step = journal.begin_step(b.id, "machine", "cnc2", "finish")
    clock.at += 5
    journal.end_step(step.id, "failed", "stalled", hold="needs inspection")
    journal.scrap_part(b.id, "broken")
    report = shift_report(journal, ["cnc1", "cnc2"], {}, 1000.0, 1100.0)
    cnc1, cnc2 = report.machines
    assert (cnc1.steps_ended, cnc1.steps_good) == (2, 1)
    assert (cnc2.steps_ended, cnc2.steps_good) == (1, 0)
    # Of the parts ended in the window, B (scrapped) is the only one: neither cut it well.
    assert (cnc1.parts_ended, cnc1.parts_good, cnc1.quality) == (1, 0, 0.0)
    assert (cnc2.parts_ended, cnc2.parts_good, cnc2.quality) == (1, 0, 0.0)
    assert cnc1.performance == 1.0  # no model: a step counts its own time
    journal.close()
