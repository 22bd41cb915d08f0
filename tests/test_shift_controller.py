"""The shift report's account of the controller: the window's time split into running, paused,
stopped and not known (adding up to the window), and who paused and resumed it, as the
journal recorded them (the caller and their role, not "the operator" for everyone).

Exact figures from a journal built through the real journal API (a clock the test sets), and
a real controller on the emulated cell (virtual time) paused by an operator's token and
resumed by an engineer's, through the control API.
"""

from __future__ import annotations

import asyncio
import json
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import pytest

from cellctl.cell.journal import Journal
from cellctl.cell.shift import shift_report
from cellctl.clock import current_clock
from cellctl.service.access import AttachedCell, LocalCell
from cellctl.service.methods import Dispatcher
from cellctl.service.rpc import Caller
from cellctl.testing.rig import CellRig
from cellctl.ui.report_cli import WIDTH, shift_csv, shift_lines

from .conftest import SetClock as Clock


def _iso(t: float) -> str:
    """``t`` as --from and --to take it (local time, to the microsecond)."""
    return datetime.fromtimestamp(t).isoformat()


@dataclass
class Order:
    id: str
    part_type: str
    qty: int


def _journal(tmp_path: Path, *, stopped: bool = True) -> Journal:
    """A controller started at 900, paused 1100-1130, ended without a word after its last
    step (1140-1150), started again at 1200, paused by the emergency stop 1250-1260, and
    stopped at 1300 (or, without ``stopped``, ended unheard after its step 1270-1280)."""
    clock = Clock(900.0)
    j = Journal(tmp_path / "journal.sqlite3", clock=clock)
    (part,) = j.create_parts(Order("O", "base", 1))
    j.note_controller("started")
    clock.at = 1100
    j.note_controller("paused", by="token:olga (operator)")
    clock.at = 1130
    j.note_controller("resumed", by="token:eve (engineer)")
    clock.at = 1140
    step = j.begin_step(part.id, "machine", "cnc1", "rough")
    clock.at = 1150
    j.end_step(step.id, "finished", route_index=1)
    clock.at = 1200  # a crash, a kill: no "stopped" before this start
    j.note_controller("started")
    clock.at = 1250
    j.note_controller("paused", why="emergency stop pressed")
    clock.at = 1260
    j.note_controller("resumed", by="token:eve (engineer)")
    if stopped:
        clock.at = 1300
        j.note_controller("stopped")
    else:
        clock.at = 1270
        step = j.begin_step(part.id, "machine", "cnc1", "finish")
        clock.at = 1280
        j.end_step(step.id, "finished", route_index=2)
    return j


def test_the_windows_time_adds_up_and_says_who(tmp_path: Path) -> None:
    journal = _journal(tmp_path)
    report = shift_report(journal, ["cnc1"], {}, 1000.0, 1400.0).as_dict()
    split = {k: report[k] for k in ("running_s", "paused_s", "stopped_s", "not_known_s")}
    # Running 1000-1100, 1130-1150 (its last step), 1200-1250, 1260-1300; paused 1100-1130
    # and 1250-1260; not known 1150-1200 (it ended unheard); stopped from 1300.
    assert split == {"running_s": 210.0, "paused_s": 40.0, "stopped_s": 100.0,
                     "not_known_s": 50.0}  # fmt: skip
    assert sum(split.values()) == 400.0
    events = [(e["time"], e["event"], e["by"]) for e in report["controller_events"]]
    assert events == [
        (1100.0, "paused", "token:olga (operator)"),
        (1130.0, "resumed", "token:eve (engineer)"),
        (1150.0, "ended unheard", ""),
        (1200.0, "started", ""),
        (1250.0, "paused", ""),
        (1260.0, "resumed", "token:eve (engineer)"),
        (1300.0, "stopped", ""),
    ]

    lines = shift_lines(report)
    assert max(len(x) for x in lines) <= WIDTH
    text = "\n".join(lines)
    assert "controller: running 0:03:30, paused 40.0 s, stopped 0:01:40, not known 50.0 s" in text
    assert "paused by token:olga (operator)" in text
    assert "resumed by token:eve (engineer)" in text
    assert "resumed by the operator" not in text
    assert "paused: emergency stop pressed" in text
    assert "ended without stopping (a crash, a kill?)" in text
    assert "controller,,paused_s,40.0" in shift_csv(report)

    # Before the journal kept the controller's state: not known, all of it.
    old = shift_report(journal, ["cnc1"], {}, 0.0, 800.0).as_dict()
    assert (old["not_known_s"], old["running_s"], old["controller_events"]) == (800.0, 0.0, [])
    journal.close()


def test_a_controller_gone_unheard_is_not_counted_running(tmp_path: Path) -> None:
    journal = _journal(tmp_path, stopped=False)
    # A controller runs (the API's own): it runs to the window's end.
    running = shift_report(journal, ["cnc1"], {}, 1000.0, 1400.0).as_dict()
    assert (running["running_s"], running["not_known_s"]) == (310.0, 50.0)
    # None runs now: the last one ended unheard after its last step (1280).
    gone = shift_report(journal, ["cnc1"], {}, 1000.0, 1400.0, running_now=False).as_dict()
    assert (gone["running_s"], gone["not_known_s"]) == (190.0, 170.0)
    assert gone["controller_events"][-1]["event"] == "ended unheard"
    journal.close()


@pytest.mark.virtual
async def test_pause_and_resume_on_a_real_controller(tmp_path: Path) -> None:
    async with CellRig(tmp_path) as rig:
        rig.post("wax-robot-base", 1, "A")
        controller = await rig.start_controller()
        api = Dispatcher(AttachedCell(controller))
        olga, eve = Caller("token:olga", "operator"), Caller("token:eve", "engineer")
        await api.call("cell.pause", {}, caller=olga)
        await asyncio.sleep(120)  # the cell stands paused two minutes (virtual time)
        await api.call("cell.resume", {}, caller=eve)
        await rig.wait_for(rig.all_done, "order A done", timeout=120)
        # The controller's own event names who resumed it, not "the operator".
        said = [e.text for e in controller.events]
        assert "resumed by token:eve (engineer)" in said, said
        await rig.stop_controller()
        await asyncio.sleep(60)  # a minute stopped before the shift's end
        end = current_clock().now()
        start = controller.started_at  # the shift: from the controller's start

        found = await Dispatcher(LocalCell(tmp_path, {})).call(
            "report.shift", {"since": start, "until": end}
        )
        split = [found[k] for k in ("running_s", "paused_s", "stopped_s", "not_known_s")]
        assert sum(split) == pytest.approx(end - start, abs=1e-3)
        assert found["paused_s"] == pytest.approx(120.0, abs=1.0)
        assert found["stopped_s"] == pytest.approx(60.0, abs=1.0)
        assert found["not_known_s"] == pytest.approx(0.0, abs=1e-3)
        events = [(e["event"], e["by"]) for e in found["controller_events"]]
        assert events == [
            ("started", ""),
            ("paused", "token:olga (operator)"),
            ("resumed", "token:eve (engineer)"),
            ("stopped", ""),
        ]

        window = ["--from", _iso(start - 1), "--to", _iso(end)]  # the start included
        result = await rig.cli("report", "shift", "--json", *window)
        assert json.loads(result.output)["controller_events"] == found["controller_events"]
        table = await rig.cli("report", "shift", *window)
        assert "controller: running " in table.output, table.output
        assert "paused by token:olga (operator)" in table.output, table.output
        assert "resumed by token:eve (engineer)" in table.output, table.output


@pytest.mark.virtual
async def test_an_emergency_stop_pauses_on_record_and_is_handed_over(tmp_path: Path) -> None:
    async with CellRig(tmp_path) as rig:
        controller = await rig.start_controller()
        eve = Caller("token:eve", "engineer")
        await Dispatcher(AttachedCell(controller)).call(
            "cell.estop", {"reason": "smoke at cnc1"}, caller=eve
        )
        await asyncio.sleep(30)  # the cell stands stopped half a minute (virtual time)
        await rig.stop_controller()
        start, end = controller.started_at, current_clock().now()

        found = await Dispatcher(LocalCell(tmp_path, {})).call(
            "report.shift", {"since": start, "until": end}
        )
        (paused,) = [e for e in found["controller_events"] if e["event"] == "paused"]
        assert (paused["by"], paused["why"]) == (
            "token:eve (engineer)",
            "emergency stop: smoke at cnc1",
        )
        assert found["paused_s"] == pytest.approx(30.0, abs=1.0)
        # The stop's alarm is left open: the next shift is told.
        (alarm,) = found["open_alarms_at_end"]
        assert (alarm["machine"], alarm["code"], alarm["acknowledged"]) == ("cell", "estop", False)
        lines = "\n".join(shift_lines(found))
        assert "paused by token:eve (engineer): emergency stop: smoke at cnc1" in lines
        assert "at the window's end: no part held, 1 alarm open (1 not acknowledged)" in lines
