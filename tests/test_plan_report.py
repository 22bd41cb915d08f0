"""A plan's report read from a journal (the engine writes the same schema as a real cell):
per order when it finishes against its due time, parts made, utilizations over the plan's
span, and the demo's Gantt chart with the axis in wall-clock time and the fault windows."""

from __future__ import annotations

import re
from datetime import datetime
from pathlib import Path

from cellctl.cell.config import load_cell
from cellctl.cell.journal import Journal, open_journal
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.mailbox.base import Order
from cellctl.plan.engine import FaultWindow, PlanOrder
from cellctl.plan.report import LATE, ON_TIME, OPEN, machines_of, plan_report, plan_svg
from tests.test_demo import _ListClock

T0 = datetime(2026, 11, 25, 6, 0).timestamp()


def _make(journal: Journal, now: list[float], order_id: str, part_type: str, qty: int) -> None:
    """Each part of the order: a transfer (2 s), a cut on cnc1 (100 s), one on cnc2 (50 s),
    back out (2 s), one part after the other."""
    order = Order(order_id, part_type, qty, 0, "accepted", now[0], now[0])
    for part in journal.create_parts(order):
        for kind, machine, program, span in (
            ("transfer", "robot", "conveyor_to_cnc1", 2.0),
            ("machine", "cnc1", "rough", 100.0),
            ("transfer", "robot", "cnc1_to_cnc2", 2.0),
            ("machine", "cnc2", "finish", 50.0),
            ("transfer", "robot", "cnc2_to_conveyor", 2.0),
        ):
            step = journal.begin_step(part.id, kind, machine, program)
            now[0] += span
            journal.end_step(step.id, "finished")
        journal.finish_part(part.id)


def test_the_report_says_per_order_when_it_finishes_against_its_due_time(tmp_path: Path) -> None:
    now = [T0 + 10.0]  # the first step 10 s after the plan's start
    with open_journal(tmp_path, clock=_ListClock(now)) as journal:
        _make(journal, now, "A", "wax-robot-base", 2)  # done at T0 + 10 + 2 * 156 = T0 + 322
        a_done = now[0]
        _make(journal, now, "B", "wax-toy-mill-table", 1)  # done at T0 + 478
        b_done = now[0]
        orders = [
            PlanOrder("A", "wax-robot-base", 2, due=a_done + 1),  # on time
            PlanOrder("B", "wax-toy-mill-table", 1, due=b_done - 60),  # late by 60 s
            PlanOrder("C", "wax-robot-base", 3, due=T0 + 400),  # never made: due passed
            PlanOrder("D", "wax-robot-base", 1, due=T0 + 9000),  # never made: due later
        ]
        fault = FaultWindow("cnc2", "down", T0 + 100, T0 + 200)
        config = load_cell(EXAMPLE_CELL)
        report = plan_report(
            journal, config, orders, start=T0, until=T0 + 3600, ended=T0 + 600, faults=[fault]
        )
        steps, types = journal.steps(), {p.id: p.part_type for p in journal.parts()}
    by_id = {o.order_id: o for o in report.orders}
    assert (by_id["A"].verdict, by_id["A"].finished, by_id["A"].made) == (ON_TIME, a_done, 2)
    assert (by_id["B"].verdict, by_id["B"].late_s) == (LATE, 60.0)
    assert (by_id["C"].verdict, by_id["C"].finished, by_id["C"].late_s) == (LATE, None, 200.0)
    assert by_id["D"].verdict == OPEN
    assert report.parts_made == {"wax-robot-base": 2, "wax-toy-mill-table": 1}
    # Utilization: time in steps over the plan's span (start to where it stopped, 600 s).
    assert report.utilization["cnc1"] == 300 / 600
    assert report.utilization["cnc2"] == 150 / 600
    assert abs(report.utilization["robot"] - 18 / 600) < 1e-9
    text = "\n".join(report.lines())
    assert "A            wax-robot-base" in text and "on time" in text
    assert "late by 0:01:00" in text and "late by at least 0:03:20" in text
    assert "fault: cnc2 down from Wed 06:01:40 to Wed 06:03:20" in text
    assert "utilization: robot 3.0%, cnc1 50.0%, cnc2 25.0%" in text

    svg = plan_svg([report], [steps], [types], machines_of(config))
    assert svg.count('class="step machine"') == 6 and svg.count('class="step transfer"') == 9
    ticks = re.findall(r'text-anchor="middle">([^<]+)</text>', svg)
    assert ticks[0] == "06:00" and ticks[-1] == "07:00", ticks  # wall-clock time, start to end
    [window] = re.findall(r'<rect x="([\d.]+)" y="[\d.]+" width="([\d.]+)"[^>]*class="window"', svg)
    assert abs(float(window[0]) - (90 + 100 / 3600 * 900)) < 1  # 100 s of 3600 at 900 px
    assert abs(float(window[1]) - 100 / 3600 * 900) < 1
    assert "fault window" in svg.split('<g class="legend">', 1)[1]


def test_a_machine_down_while_it_cuts_is_down_not_also_busy(tmp_path: Path) -> None:
    """cnc1 cuts from 06:00:10 to 06:01:50; it is taken out of service at 06:00:50 (it
    finishes the cut, as an operator's "out of service" lets it) and back at 06:03:20, and
    cnc2 is alarmed from 06:01:00 to 06:02:00 while it cuts: each machine's busy and down
    shares add up to at most the plan's span, its down time counting as down only."""
    now = [T0 + 10.0]
    with open_journal(tmp_path, clock=_ListClock(now)) as journal:
        order = Order("A", "wax-robot-base", 1, 0, "accepted", now[0], now[0])
        [part] = journal.create_parts(order)
        cut = journal.begin_step(part.id, "machine", "cnc1", "rough")
        now[0] = T0 + 50
        journal.set_machine_service("cnc1", False, "plan: down")
        now[0] = T0 + 110
        journal.end_step(cut.id, "finished")
        second = journal.begin_step(part.id, "machine", "cnc2", "finish")  # 06:01:50 on
        now[0] = T0 + 120
        journal.raise_alarm("cnc2", "stall", "cnc2 stalled")  # 06:02:00
        now[0] = T0 + 180
        journal.return_to_normal("cnc2", ["stall"])
        now[0] = T0 + 200
        journal.set_machine_service("cnc1", True)
        journal.end_step(second.id, "finished")
        journal.finish_part(part.id)
        report = plan_report(
            journal,
            load_cell(EXAMPLE_CELL),
            [PlanOrder("A", "wax-robot-base", 1)],
            start=T0,
            until=T0 + 3600,
            ended=T0 + 300,
        )
    # cnc1: busy 10 s to 50 s only (the rest of its cut is down), down 50 s to 200 s.
    assert (report.busy_s["cnc1"], report.down_s["cnc1"]) == (40.0, 150.0)
    # cnc2: its cut from 110 s to 200 s, less the alarm from 120 s to 180 s.
    assert (report.busy_s["cnc2"], report.down_s["cnc2"]) == (30.0, 60.0)
    assert report.utilization["cnc1"] == round(40 / 300, 4)
    for machine in report.busy_s:
        assert report.busy_s[machine] + report.down_s[machine] <= 300, machine
    text = "\n".join(report.lines())
    assert "utilization: robot 0.0%, cnc1 13.3%, cnc2 10.0%" in text
    assert "down: cnc1 0:02:30 (50.0%), cnc2 0:01:00 (20.0%)" in text
