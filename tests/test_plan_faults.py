"""Fault windows in a plan: every fault's name and argument checked against the machine's own
emulator before anything runs (from the command line, a replayed inputs.json and the engine),
any switch an emulator has played (a UR's protective stop among them, ended by the plan's
operator at the pendant), and a play that an error ends mid-way ending cleanly."""

from __future__ import annotations

import json
import logging
import re
import shutil
import subprocess
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from cellctl.cell.journal import Journal
from cellctl.clock import run_virtual
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.errors import UsageError
from cellctl.plan import engine
from cellctl.plan.engine import FaultWindow, PlanInputs, PlanOrder, PlanRun, simulate
from cellctl.plan.inputs import save_inputs
from cellctl.ui.cli import main

from .conftest import CELLCTL

TENDING = Path(__file__).resolve().parent.parent / "examples" / "cell-tending"
#: The plans start on a Wednesday at 14:00 local time.
START = "2026-11-25T14:00"
T0 = datetime(2026, 11, 25, 14, 0).timestamp()


def plan(*args: str, expect: int = 0) -> Any:
    """``cellctl plan ARGS`` in this process (its plan on its own virtual-time loop)."""
    result = CliRunner().invoke(main, ["plan", *args])
    assert result.exit_code == expect, result.output + repr(result.exception)
    return result


@pytest.mark.parametrize(
    ("cell", "fault", "message"),
    [
        (EXAMPLE_CELL, "plc:stuck-door=abc@14:00", "stuck-door needs a mill number 1 or 2"),
        (EXAMPLE_CELL, "cnc1:noise=zz@14:00", r"noise takes RATE\[,SEED\]"),
        (EXAMPLE_CELL, "cnc1:noise@14:00", r"noise takes RATE\[,SEED\]"),
        (EXAMPLE_CELL, "robot:corrupt-checksum=x@14:00", "corrupt-checksum needs a count"),
        (EXAMPLE_CELL, "cnc2:down=2@14:00", "takes no argument"),
        # A window that opens long after the one part is done: checked all the same.
        (EXAMPLE_CELL, "cnc2:drop=abc@15:50", "drop takes a line count, not 'abc'"),
        (TENDING, "vf2:line-lag=soon@14:00", "line-lag: 'soon' is not a number"),
        (TENDING, "robot:protective-stop@14:00", r"unknown \(known: down, protective_stop"),
    ],
)
def test_a_bad_fault_is_refused_in_its_own_words_before_anything_runs(
    cell: Path, fault: str, message: str
) -> None:
    part = "bracket:1" if cell == TENDING else "wax-robot-base:1"
    args = ["--dir", str(cell), "--add", part, "--start", START, "--shift", "2h"]
    result = plan(*args, "--fault", fault, expect=2)
    assert re.search(message, result.stderr), result.stderr
    assert "plan of" not in result.stdout  # nothing played


def test_the_command_refuses_a_bad_argument_without_a_traceback(tmp_path: Path) -> None:
    """The walkthrough's command, as a user runs it (its own process): one line, exit 2."""
    done = subprocess.run(
        [*CELLCTL, "plan", "--dir", str(EXAMPLE_CELL), "--add", "wax-robot-base:1",
         "--start", START, "--shift", "2h", "--fault", "plc:stuck-door=abc@14:00"],
        capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.strip().splitlines() == [
        "error: fault plc:stuck-door=abc: stuck-door needs a mill number 1 or 2, not 'abc'"
    ]
    assert done.stdout == ""


def test_a_replayed_inputs_file_with_a_bad_fault_is_refused(tmp_path: Path) -> None:
    """An inputs.json edited by hand (or saved by an older cellctl) is checked as --fault is."""
    inputs = PlanInputs(
        EXAMPLE_CELL,
        (PlanOrder("A", "wax-robot-base", 1),),
        T0,
        T0 + 7200,
        faults=(FaultWindow("plc", "stuck-door", T0 + 60, T0 + 600, "abc"),),
    )
    saved = save_inputs(inputs, ("default",), tmp_path / "out")
    result = plan("--replay", str(saved), expect=2)
    assert "stuck-door needs a mill number 1 or 2, not 'abc'" in result.stderr
    # The engine refuses it too, before it writes anything.
    with pytest.raises(UsageError, match="stuck-door needs a mill number"):
        simulate(inputs, tmp_path / "play")
    assert not (tmp_path / "play").exists()


def test_an_error_that_ends_a_play_midway_ends_it_cleanly(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The check refuses a bad argument before the play now; the play itself must still end
    cleanly on whatever error ends it mid-way (the controller and its steps stopped before
    the journal closes). Played here past the check, with a switch its emulator refuses when
    its window opens."""
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    inputs = PlanInputs(
        cell,
        (PlanOrder("A", "wax-robot-base", 2),),
        T0,
        T0 + 7200,
        faults=(FaultWindow("plc", "stuck-door", T0 + 120, None, "abc"),),
    )
    workdir = tmp_path / "play"
    workdir.mkdir()
    with caplog.at_level(logging.WARNING), pytest.raises(UsageError, match="stuck-door needs"):
        run_virtual(engine._play(inputs, workdir), start=T0 - engine.POWER_ON_S)
    problems = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert problems == [], problems
    # It ended soon after the window opened: the second part was never started.
    with Journal(workdir / "journal.sqlite3") as journal:
        assert all(s.started < T0 + 600 for s in journal.steps())
        assert all(s.ended is not None for s in journal.steps())  # nothing left running


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_a_protective_stop_is_planned_from_the_command_line(tmp_path: Path) -> None:
    """`--fault robot:protective_stop@14:00-14:20` on the cobot cell (a UR's own switch name,
    as `cellctl emulate cell --fault` takes it): the robot does nothing in the window, the
    order gets done after it."""
    common = ["--dir", str(TENDING), "--add", "bracket:2", "--start", START]
    out = tmp_path / "out"
    text = plan(*common, "--fault", "robot:protective_stop@14:00-14:20", "--out", str(out)).output
    assert "fault: robot protective_stop from Wed 14:00:00 to Wed 14:20:00" in text
    [report] = json.loads((out / "plan.json").read_text())["plans"]  # the plan printed
    closes = T0 + 20 * 60
    robot = [s for s in report["steps"] if s["machine"] == "robot"]
    assert robot and all(s["started"] >= closes for s in robot), robot
    assert report["all_finished"] and report["down_s"]["robot"] >= closes - T0 - 60


def cobot_fault(tmp_path: Path, fault: str, opens: float, closes: float) -> PlanRun:
    """The tending cell's plan of order A (2 brackets) over three hours, with the UR's
    ``fault`` switched on from ``opens`` to ``closes``."""
    inputs = PlanInputs(
        TENDING,
        (PlanOrder("A", "bracket", 2),),
        T0,
        T0 + 3 * 3600,
        faults=(FaultWindow("robot", fault, opens, closes),),
    )
    return simulate(inputs, tmp_path)


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_the_plans_operator_unlocks_a_protective_stop_after_its_window(tmp_path: Path) -> None:
    """A protective stop mid-transfer: the arm stops there and the step fails; nothing of the
    robot runs over the window; after it, the plan's operator unlocks the stop at the pendant
    (the UR's rule: nothing else ends a protective stop), clears the alarm and releases the
    part where it is, and the transfer is played again."""
    opens, closes = T0 + 45, T0 + 300  # the part on its way from the VF-2 to CNC 2
    run = cobot_fault(tmp_path, "protective_stop", opens, closes)
    with Journal(run.journal_path) as journal:
        steps = [s for s in journal.steps() if s.machine == "robot"]
        alarms = journal.alarms()
    failed = [s for s in steps if s.state == "failed"]
    assert [(s.program, s.ended is not None and opens <= s.ended < opens + 5) for s in failed] == [
        ("vf2_to_cnc2", True)
    ]
    assert not any(opens < s.started < closes for s in steps), steps
    again = [s for s in steps if s.started >= closes]
    assert again[0].program == "vf2_to_cnc2" and again[0].state == "finished"
    [alarm] = alarms
    assert "PROTECTIVE_STOP" in alarm.text and alarm.cleared_by == "plan operator"
    assert alarm.cleared is not None and alarm.cleared >= closes
    assert run.finished["A"] is not None


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_a_dropped_connection_on_the_cobot_mid_transfer_is_resolved(tmp_path: Path) -> None:
    """`robot:drop` while the UR carries a part: the links go, the step fails and the part is
    held; after the window the plan's operator waits for the arm at rest (a UR's program
    state, not an IBM 7545's), clears the alarm and releases the part, and the order gets
    done. Every wait of it has a deadline: the play ends, on its own virtual time."""
    opens, closes = T0 + 45, T0 + 300
    run = cobot_fault(tmp_path, "drop", opens, closes)
    with Journal(run.journal_path) as journal:
        alarms = journal.alarms()
        held = journal.parts(statuses=["held"])
    assert [(a.text, a.cleared_by) for a in alarms] == [
        ("link closed by the other end", "plan operator")
    ]
    assert opens <= alarms[0].raised < closes and not held
    assert run.finished["A"] is not None


def rough_cut(tmp_path: Path, *faults: FaultWindow) -> tuple[float, float, float | None]:
    """The example cell's plan of one robot base over an hour from T0: cnc1's rough cut
    (its start and end) and the order's finish."""
    inputs = PlanInputs(
        EXAMPLE_CELL, (PlanOrder("A", "wax-robot-base", 1),), T0, T0 + 3600, faults=faults
    )
    run = simulate(inputs, tmp_path / str(len(list(tmp_path.iterdir()))))
    with Journal(run.journal_path) as journal:
        [cut] = [s for s in journal.steps() if s.kind == "machine" and s.machine == "cnc1"]
    assert cut.state == "finished" and cut.ended is not None
    return cut.started, cut.ended, run.finished["A"]


@pytest.mark.parametrize("fault", ["never-ready", "stall"])
def test_a_mill_fault_come_and_gone_within_a_cut_leaves_the_cut_as_it_was(
    tmp_path: Path, fault: str
) -> None:
    """READY withheld (or CTS stuck) from the 2nd to the 3rd minute of a 12-minute cut, and
    the panel's link mode selected again after: the mill goes on cutting; READY comes at the
    block's end, as without the fault (it came at once, and the cut counted as done)."""
    started, ended, finished = rough_cut(tmp_path)
    window = FaultWindow("cnc1", fault, T0 + 120, T0 + 180)
    assert started < window.start and window.end is not None and window.end < ended
    assert rough_cut(tmp_path, window) == pytest.approx((started, ended, finished), abs=1.0)


def test_a_mill_not_ready_when_its_cut_ends_holds_the_part_until_ready(tmp_path: Path) -> None:
    started, ended, finished = rough_cut(tmp_path)
    assert finished is not None
    closes = ended + 300  # READY withheld from a minute before the cut's end to 5 min after
    window = FaultWindow("cnc1", "never-ready", ended - 60, closes)
    late_started, late_ended, late_finished = rough_cut(tmp_path, window)
    assert late_started == pytest.approx(started, abs=1.0)
    assert closes <= late_ended <= closes + 60
    assert late_finished is not None and late_finished >= finished + (closes - ended)


def test_a_failure_that_shows_after_its_window_is_resolved_all_the_same(tmp_path: Path) -> None:
    """Line noise while a block goes to cnc1 garbles it: the mill never says the block is
    done, and the controller fails the cut at its deadline, long after the window closed.
    The plan's operator is still watching (a step begun under the fault was in flight): the
    alarm is cleared, the part released, and the mill's ERROR cleared at its panel (memory
    cleared, READY again): the part is cut again and the order finishes, not left with the
    mill stuck for the rest of the plan."""
    opens, closes = T0 + 13 * 60, T0 + 14 * 60  # the second part's block goes at 13:10
    inputs = PlanInputs(
        EXAMPLE_CELL,
        (PlanOrder("A", "wax-robot-base", 2),),
        T0,
        T0 + 2 * 3600,
        faults=(FaultWindow("cnc1", "noise", opens, closes, "0.01,7"),),
    )
    run = simulate(inputs, tmp_path)
    with Journal(run.journal_path) as journal:
        failed = [s for s in journal.steps() if s.state == "failed"]
        alarms = journal.alarms()
        held = journal.parts(statuses=["held"])
        again = [s for s in journal.steps(failed[0].part_id) if s.machine == "cnc1"]
    assert [(s.machine, s.kind) for s in failed] == [("cnc1", "machine")]
    assert failed[0].started < closes and failed[0].ended is not None
    assert failed[0].ended > closes + 600  # shown long after the window
    assert [a.cleared_by for a in alarms] == ["plan operator"]
    assert held == []
    # The garbled cut once, then the whole cut again once the panel was cleared.
    assert [s.state for s in again] == ["failed", "finished"], again
    assert again[1].started >= failed[0].ended
    finished = run.finished["A"]
    assert finished is not None and finished <= inputs.until, run.finished


def base_orders(tmp_path: Path, faults: tuple[FaultWindow, ...], **kw: Any) -> PlanRun:
    """Three robot bases over two hours from T0, with ``faults``."""
    inputs = PlanInputs(
        EXAMPLE_CELL,
        (PlanOrder("A", "wax-robot-base", 3),),
        T0,
        T0 + 2 * 3600,
        faults=faults,
        **kw,
    )
    return simulate(inputs, tmp_path / str(len(list(tmp_path.iterdir()))))


def test_overlapping_windows_of_one_fault_act_as_their_union(tmp_path: Path) -> None:
    # cnc1 down 14:10-15:00 and 14:30-15:30: down until 15:30 (the first one's end put it
    # back in service while the second was open), as one window 14:10-15:30.
    both = base_orders(
        tmp_path,
        (
            FaultWindow("cnc1", "down", T0 + 600, T0 + 3600),
            FaultWindow("cnc1", "down", T0 + 1800, T0 + 5400),
        ),
    )
    union = base_orders(tmp_path, (FaultWindow("cnc1", "down", T0 + 600, T0 + 5400),))
    with Journal(both.journal_path) as journal:
        cuts = [s.started for s in journal.steps() if s.machine == "cnc1"]
    assert not any(T0 + 600 < t < T0 + 5400 for t in cuts), cuts
    assert both.finished == union.finished


def test_a_machine_out_of_service_at_the_start_stays_out_past_a_window(tmp_path: Path) -> None:
    run = base_orders(
        tmp_path,
        (FaultWindow("cnc2", "down", T0 + 600, T0 + 1200),),
        out_of_service=("cnc2",),
    )
    with Journal(run.journal_path) as journal:
        assert [s for s in journal.steps() if s.machine == "cnc2"] == []
        assert "cnc2" in journal.machines_out_of_service()
    assert run.finished["A"] is None


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_a_dr_off_window_on_the_iso_cnc_mill_ends_with_the_operators_reset(
    tmp_path: Path,
) -> None:
    """`vf2:dr-off` over half an hour from the middle of the VF-2's first cut (the
    integrator's case): the drip-feed fails on alarm 086 and the mill is not ready while DR
    is off; at the window's end the control still shows its alarm (a real one keeps it)
    until the plan's operator resets it at the control, which its host hears: the VF-2 cuts
    again at once, nothing is taken out of service after the window, and its time down is
    the window's, not the rest of the shift."""
    out = tmp_path / "out"
    start = "2026-11-25T13:59:30"  # the VF-2's first cut runs across 14:00
    args = ["--dir", str(TENDING), "--add", "bracket:2", "--start", start, "--shift", "2h"]
    plan(*args, "--fault", "vf2:dr-off@14:00-14:30", "--out", str(out))
    [report] = json.loads((out / "plan.json").read_text())["plans"]
    opens, closes = T0, T0 + 30 * 60
    vf2 = [s for s in report["steps"] if s["machine"] == "vf2"]
    assert vf2[0]["state"] == "failed" and vf2[0]["started"] < opens < vf2[0]["ended"], vf2
    assert not any(opens < s["started"] < closes for s in vf2), vf2
    after = [s for s in vf2 if s["started"] >= closes]
    assert after and all(s["state"] == "finished" for s in after), after
    alarms = report["alarms"]
    assert "DR OFF (code 86)" in alarms[0]["text"] and alarms[0]["machine"] == "vf2", alarms
    # Where the tape ended, as the DNC line says it: the operator decides at the control.
    ended = r"; (all \d+ characters of its tape were out|the tape ended at \d+ of \d+ characters)"
    assert re.search(ended, alarms[0]["text"]), alarms
    assert all(a["raised"] < closes for a in alarms), alarms  # none after the window
    assert closes - opens <= report["down_s"]["vf2"] <= closes - opens + 120, report["down_s"]
    assert report["all_finished"], report["orders"]


def test_a_dr_off_window_while_the_iso_cnc_mill_idles_is_its_alarm_and_down_time(
    tmp_path: Path,
) -> None:
    """The window opens before the VF-2's first part reaches it (the integrator's own
    command): no cut fails, yet the control shows its alarm the whole window. The cell's
    look at the idle mill finds it so: one alarm in the control's words, the VF-2 down for
    the window (not 0, not the rest of the shift), and its cuts after the reset."""
    out = tmp_path / "out"
    args = ["--dir", str(TENDING), "--add", "bracket:2", "--start", START, "--shift", "2h"]
    plan(*args, "--fault", "vf2:dr-off@14:00-14:30", "--out", str(out))
    [report] = json.loads((out / "plan.json").read_text())["plans"]
    opens, closes = T0, T0 + 30 * 60
    vf2 = [s for s in report["steps"] if s["machine"] == "vf2"]
    assert vf2 and all(s["started"] >= closes for s in vf2), vf2
    assert all(s["state"] == "finished" for s in vf2), vf2
    [alarm] = [a for a in report["alarms"] if a["machine"] == "vf2"]
    assert "086" in alarm["text"] and opens <= alarm["raised"] < opens + 60, alarm
    assert closes - opens - 60 <= report["down_s"]["vf2"] <= closes - opens + 120, report
    assert report["all_finished"], report["orders"]
