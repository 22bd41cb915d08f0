"""The shift report's time accounting under faults: failed steps, a PLC not answering, an
emergency stop over a machine's own alarm (docs/cell.md, "The shift report").

A supervisor reads: a failed step's time while its machine was up is run time that made
nothing (a performance loss, ``failed_s``); its time while the machine was down (the cell
stopped) is down time only; a stop of the whole cell (the PLC not answering, as the E-stop)
is down time for every machine, once where a machine's own alarm overlaps it.

The journal is written through the real journal API, at times a test clock sets; every
expected figure is worked out below from those times.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import pytest

from cellctl.cell.causes import ESTOP
from cellctl.cell.journal import Journal, Part, open_journal
from cellctl.cell.shift import shift_report
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.ui.report_cli import WIDTH, shift_csv, shift_html, shift_lines

from .conftest import SetClock as Clock

#: The window's start: 2026-11-25 06:00 local; every time below is seconds after it.
T0 = datetime(2026, 11, 25, 6, 0).timestamp()
END = 400.0
#: The PLC not answering (its link alarm active), 1:07 as in the tester's run; cleared later.
LINK = (40.0, 107.0)
#: The PLC's emergency stop, and cnc2's own alarm overlapping its end.
STOP = (300.0, 340.0)
CNC2_STATUS = (320.0, 360.0)
#: The robot's first try at B's load, failed by the PLC's deadline just after the alarm.
FIRST_TRY = (35.0, 41.0)
#: Its retries while the PLC did not answer (attempts 2 to 7), each failed: inside LINK.
RETRIES = [(45.0 + 10 * k, 48.0 + 10 * k) for k in range(6)]
#: The robot's steps that finished: A's load, B's load once the PLC answered, A's unload.
ROBOT_DONE = [(10.0, 30.0), (110.0, 130.0), (345.0, 365.0)]
#: A's unload cut short by the emergency stop (failed).
CUT_SHORT = (290.0, 310.0)
#: cnc1: A's cut, which ran on while the PLC did not answer and finished; C's cut that
#: failed (a stall, nothing stopped), and C's cut again, finished.
CNC1_DONE = [(90.0, 150.0), (215.0, 245.0)]
CNC1_FAILED = (200.0, 210.0)
#: The machines' ideal times (their models'), s.
IDEAL = {"robot/load": 15.0, "robot/unload": 15.0, "cnc1/rough": 25.0}


@dataclass
class Order:
    id: str
    part_type: str
    qty: int


def _length(span: tuple[float, float]) -> float:
    return span[1] - span[0]


def _step(
    journal: Journal,
    clock: Clock,
    part: Part,
    kind: str,
    machine: str,
    program: str,
    span: tuple[float, float],
    state: str,
) -> None:
    clock.at = T0 + span[0]
    step = journal.begin_step(part.id, kind, machine, program)
    clock.at = T0 + span[1]
    journal.end_step(step.id, state, "" if state == "finished" else "PLC not answering")


def write_journal(journal: Journal, clock: Clock) -> None:
    """The faults' journal: the steps and alarms above, parts A, B and C all finished."""
    a, b, c = journal.create_parts(Order("O", "base", 3))
    # The alarms: the PLC's link, the E-stop, cnc2's own status alarm (returned, cleared).
    for machine, code, text, (t0, t1) in (
        ("plc", "link", "PLC not answering", LINK),
        (ESTOP.machine, ESTOP.code, ESTOP.text, STOP),
        ("cnc2", "status", "servo error", CNC2_STATUS),
    ):
        clock.at = T0 + t0
        alarm, _ = journal.raise_alarm(machine, code, text)
        clock.at = T0 + t1
        journal.return_to_normal(machine, [code])
        clock.at = T0 + t1 + 5
        journal.clear_alarm(alarm.id)
    _step(journal, clock, a, "transfer", "robot", "load", ROBOT_DONE[0], "finished")
    _step(journal, clock, b, "transfer", "robot", "load", FIRST_TRY, "failed")
    for retry in RETRIES:
        _step(journal, clock, b, "transfer", "robot", "load", retry, "failed")
    _step(journal, clock, b, "transfer", "robot", "load", ROBOT_DONE[1], "finished")
    _step(journal, clock, a, "machine", "cnc1", "rough", CNC1_DONE[0], "finished")
    _step(journal, clock, c, "machine", "cnc1", "rough", CNC1_FAILED, "failed")
    _step(journal, clock, c, "machine", "cnc1", "rough", CNC1_DONE[1], "finished")
    _step(journal, clock, a, "transfer", "robot", "unload", CUT_SHORT, "failed")
    _step(journal, clock, a, "transfer", "robot", "unload", ROBOT_DONE[2], "finished")
    clock.at = T0 + 370
    for part in (a, b, c):  # no part was lost
        journal.finish_part(part.id)


# What the report should say, from the times above.
#: The robot's run time: its finished steps, the first try until the PLC's alarm, the unload
#: until the stop; nothing of the retries, all inside the PLC's alarm.
ROBOT_FAILED_UP = (LINK[0] - FIRST_TRY[0]) + (STOP[0] - CUT_SHORT[0])
ROBOT_RUN = sum(map(_length, ROBOT_DONE)) + ROBOT_FAILED_UP
#: A whole-cell stop is down time for every machine: the PLC's alarm and the E-stop.
CELL_DOWN = _length(LINK) + _length(STOP)
#: cnc2: the E-stop and its own alarm overlap from 320 s to 340 s: counted once.
CNC2_DOWN = _length(LINK) + (CNC2_STATUS[1] - STOP[0])
#: cnc1's failed cut was while all was well: all of it is run time (a performance loss); its
#: cut under the PLC's alarm finished, so it keeps all its time.
CNC1_RUN = sum(map(_length, CNC1_DONE)) + _length(CNC1_FAILED)


def _report(journal: Journal) -> dict[str, dict[str, object]]:
    found = shift_report(journal, ["robot", "cnc1", "cnc2", "plc"], IDEAL, T0, T0 + END)
    return {m.machine: vars(m) for m in found.machines}


def test_failed_steps_and_whole_cell_stops(tmp_path: Path) -> None:
    clock = Clock(T0)
    with Journal(tmp_path / "journal.sqlite3", clock=clock) as journal:
        write_journal(journal, clock)
        m = _report(journal)
        robot, cnc1, cnc2 = m["robot"], m["cnc1"], m["cnc2"]

        # The robot: the retries under the PLC's alarm are down time, not run time as well.
        assert robot["production_s"] == pytest.approx(ROBOT_RUN)
        assert robot["down_s"] == pytest.approx(CELL_DOWN)
        assert robot["production_s"] + robot["down_s"] <= END
        assert robot["failed_s"] == pytest.approx(ROBOT_FAILED_UP)
        assert robot["steps_failed"] == 1 + len(RETRIES) + 1
        assert robot["steps_ended"] == robot["steps_failed"] + len(ROBOT_DONE)
        assert robot["availability"] == pytest.approx(ROBOT_RUN / END, abs=1e-4)
        # The failed steps' time up earns nothing: performance is the finished steps' ideal.
        ideal = 2 * IDEAL["robot/load"] + IDEAL["robot/unload"]
        assert robot["ideal_s"] == pytest.approx(ideal)
        assert robot["performance"] == pytest.approx(ideal / ROBOT_RUN, abs=1e-4)
        assert robot["quality"] == 1.0  # every part finished in the end

        # cnc1: its cut under the PLC's alarm finished (it made A): all its time is run time;
        # the PLC's alarm is its down time all the same (nothing new could start).
        assert cnc1["production_s"] == pytest.approx(CNC1_RUN)
        assert cnc1["failed_s"] == pytest.approx(_length(CNC1_FAILED))
        assert cnc1["steps_failed"] == 1
        assert cnc1["down_s"] == pytest.approx(CELL_DOWN)
        assert cnc1["performance"] == pytest.approx(2 * IDEAL["cnc1/rough"] / CNC1_RUN, abs=1e-4)

        # cnc2: no steps; the PLC's alarm, and the E-stop with its own alarm once.
        assert cnc2["down_s"] == pytest.approx(CNC2_DOWN)
        assert (cnc2["production_s"], cnc2["failed_s"], cnc2["steps_failed"]) == (0.0, 0.0, 0)
        # The PLC: its own link alarm and the stop, each once.
        assert m["plc"]["down_s"] == pytest.approx(CELL_DOWN)


def test_downtime_by_reason_lists_a_whole_cell_stop_once(tmp_path: Path) -> None:
    clock = Clock(T0)
    with Journal(tmp_path / "journal.sqlite3", clock=clock) as journal:
        write_journal(journal, clock)
        report = shift_report(journal, ["robot", "cnc1", "cnc2"], IDEAL, T0, T0 + END)
    reasons = {(d["machine"], d["reason"]): d["seconds"] for d in report.downtime_by_reason}
    assert reasons == {
        ("cell", "alarm: plc link"): _length(LINK),
        ("cell", "alarm: plc estop"): _length(STOP),
        ("plc", "alarm: link"): _length(LINK),
        ("plc", "alarm: estop"): _length(STOP),
        ("cnc2", "alarm: status"): _length(CNC2_STATUS),
    }
    # The table says the failed steps and their run time, at 80 columns.
    data = report.as_dict()
    lines = shift_lines(data, "a cell")
    assert max(map(len, lines)) <= WIDTH
    at = lines.index("failed steps, their run time (a performance loss):")
    assert lines[at + 1].split() == ["robot", f"{1 + len(RETRIES) + 1}", "steps,",
                                     f"{ROBOT_FAILED_UP:.1f}", "s"]  # fmt: skip
    assert lines[at + 2].split() == ["cnc1", "1", "step,", f"{_length(CNC1_FAILED):.1f}", "s"]
    assert lines[at + 3] == ""  # cnc2 failed nothing: not listed
    rows = shift_csv(data).splitlines()
    assert f"machine,robot,failed_s,{ROBOT_FAILED_UP},robot" in rows
    assert f"<td>1 step, {_length(CNC1_FAILED):.1f} s</td>" in shift_html(data, [], "a cell")


def test_a_window_inside_the_plcs_alarm(tmp_path: Path) -> None:
    # After the first try ended, only retries, all under the PLC's alarm: the robot was down,
    # never running.
    clock = Clock(T0)
    with Journal(tmp_path / "journal.sqlite3", clock=clock) as journal:
        write_journal(journal, clock)
        start, end = T0 + FIRST_TRY[1] + 1, T0 + LINK[1] - 1
        (robot,) = shift_report(journal, ["robot"], IDEAL, start, end).machines
    assert robot.production_s == 0.0 and robot.failed_s == 0.0
    assert robot.down_s == pytest.approx(end - start)
    assert robot.steps_failed == len(RETRIES)
    assert robot.availability == 0.0 and robot.performance is None


def test_the_command_reports_the_same(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    clock = Clock(T0)
    with open_journal(cell, clock=clock) as journal:
        write_journal(journal, clock)
    window = ["--from", datetime.fromtimestamp(T0).isoformat()]
    window += ["--to", datetime.fromtimestamp(T0 + END).isoformat()]
    command = [str(Path(sys.executable).with_name("cellctl")), "--cell", str(cell)]
    done = subprocess.run(
        [*command, "report", "shift", "--json", *window],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    m = {x["machine"]: x for x in found["machines"]}
    assert set(m) == {"robot", "cnc1", "cnc2"}
    assert m["robot"]["production_s"] == pytest.approx(ROBOT_RUN)
    assert m["robot"]["failed_s"] == pytest.approx(ROBOT_FAILED_UP)
    assert m["robot"]["steps_failed"] == 1 + len(RETRIES) + 1
    assert m["robot"]["availability"] == pytest.approx(ROBOT_RUN / END, abs=1e-4)
    for name in ("robot", "cnc1"):
        assert m[name]["down_s"] == pytest.approx(CELL_DOWN), name
    assert m["cnc2"]["down_s"] == pytest.approx(CNC2_DOWN)
    assert m["cnc1"]["production_s"] == pytest.approx(CNC1_RUN)
    assert found["parts_good"] == 3
