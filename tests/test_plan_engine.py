"""The plan engine: the real controller, drivers and emulators of the lab cell on virtual time,
orders played to their end or to ``until``, fault windows applied at their times, inputs the
cell cannot take refused before anything runs.
"""

from __future__ import annotations

import re
import shutil
from dataclasses import replace
from datetime import datetime
from pathlib import Path

import pytest

from cellctl.cell.config import load_cell
from cellctl.cell.journal import Journal
from cellctl.cell.model import ControllerOptions
from cellctl.cell.physics import physical_durations
from cellctl.cell.scheduler import PartState, next_transfer
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.errors import UsageError
from cellctl.plan.engine import (
    FaultWindow,
    HeldPart,
    PartAt,
    PlanInputs,
    PlanOrder,
    PlanRun,
    check_inputs,
    simulate,
)
from cellctl.plan.when import PLAN_POLL_S

START = datetime(2026, 11, 27, 6, 0).timestamp()
ORDER = PlanOrder("A", "wax-robot-base", 1)
SHIFT = PlanInputs(EXAMPLE_CELL, (ORDER,), START, START + 8 * 3600)


def relative(t: float | None) -> float | None:
    return None if t is None else t - START


def test_a_machine_down_for_a_window_holds_back_its_steps(tmp_path: Path) -> None:
    down = FaultWindow("cnc2", "down", START + 100, START + 1000)
    run = simulate(replace(SHIFT, faults=(down,)), tmp_path)
    with Journal(run.journal_path) as journal:
        steps = journal.steps()
        service = journal.service_log()
    assert [(s.kind, s.machine, s.state) for s in steps] == [
        ("transfer", "robot", "finished"),
        ("machine", "cnc1", "finished"),
        ("transfer", "robot", "finished"),
        ("machine", "cnc2", "finished"),
        ("transfer", "robot", "finished"),
    ]
    # The rough cut was done long before cnc2 came back: the part waited for it.
    assert steps[1].ended is not None and steps[1].ended < down.end - 200
    assert steps[2].started >= down.end
    assert [(relative(t), name, up) for t, name, up, _ in service] == [
        (100.0, "cnc2", False),
        (1000.0, "cnc2", True),
    ]
    finished = run.finished["A"]
    assert finished is not None and run.ended == finished
    # It finishes what the machines take after the window: load, finish cut, unload.
    phys = physical_durations(load_cell(EXAMPLE_CELL))
    cut = phys.machining_s[("cnc2", "robot_base_finish_cnc2")]
    assert finished - down.end > cut
    assert run.wall_s > 0 and run.mailbox_path is not None and run.mailbox_path.exists()


def test_a_fault_switch_over_a_window_then_the_operator_resolves(tmp_path: Path) -> None:
    servo = FaultWindow("robot", "servo-error", START + 700, START + 900)
    run = simulate(replace(SHIFT, faults=(servo,)), tmp_path)
    with Journal(run.journal_path) as journal:
        steps = journal.steps()
        alarms = journal.alarms()
    # The fault was seen as itself, while it was on, and the plan's operator cleared it.
    assert [(a.machine, a.text, a.cleared_by) for a in alarms] == [
        ("robot", "servo error", "plan operator")
    ]
    assert servo.start <= alarms[0].raised < servo.end
    # No transfer ran while the robot was faulted; the order still got done after it.
    for s in steps:
        if s.kind == "transfer":
            assert s.ended is not None
            assert s.ended <= servo.start or s.started >= servo.end
    assert all(s.state == "finished" for s in steps) and len(steps) == 5
    assert run.finished["A"] is not None and run.finished["A"] > servo.end


def test_a_part_held_at_the_start_blocks_its_mill_until_the_end(tmp_path: Path) -> None:
    held = HeldPart("X", "wax-robot-base", "cnc2", route_index=1)
    inputs = replace(SHIFT, until=START + 1500, held=(held,))
    run = simulate(inputs, tmp_path)
    assert run.ended == inputs.until
    assert run.finished == {"A": None}
    with Journal(run.journal_path) as journal:
        parts = {p.id: (p.location, p.status) for p in journal.parts()}
        steps = journal.steps()
    assert parts == {"X~held1-1": ("cnc2", "held"), "A-1": ("cnc1", "waiting")}
    assert [(s.part_id, s.machine) for s in steps] == [("A-1", "robot"), ("A-1", "cnc1")]


def test_a_part_under_way_is_taken_up_where_it_is(tmp_path: Path) -> None:
    # Two parts, one of them cut at cnc1 and carried to cnc2 already (a running cell's).
    order = PlanOrder("A", "wax-robot-base", 2, under_way=(PartAt("cnc2", 1),))
    run = simulate(replace(SHIFT, orders=(order,)), tmp_path / "under-way")
    with Journal(run.journal_path) as journal:
        steps = [(s.part_id, s.kind, s.machine, s.state) for s in journal.steps()]
        parts = {p.id: p.status for p in journal.parts()}
    assert parts == {"A-1": "done", "A-2": "done"}
    # A-1 is finished where it is and unloaded; A-2 goes the whole route.
    assert [s[1:] for s in steps if s[0] == "A-1"] == [
        ("machine", "cnc2", "finished"),
        ("transfer", "robot", "finished"),
    ]
    assert [s[1:3] for s in steps if s[0] == "A-2"] == [
        ("transfer", "robot"),
        ("machine", "cnc1"),
        ("transfer", "robot"),
        ("machine", "cnc2"),
        ("transfer", "robot"),
    ]
    # The finishing cut begins at once, with nothing to load.
    assert steps[0][:3] == ("A-1", "machine", "cnc2")
    fresh = simulate(replace(SHIFT, orders=(replace(order, under_way=()),)), tmp_path / "fresh")
    done, done_fresh = run.finished["A"], fresh.finished["A"]
    assert done is not None and done_fresh is not None and done < done_fresh


TENDING = EXAMPLE_CELL.parents[3] / "examples" / "cell-tending"


@pytest.mark.parametrize(
    ("cell", "order", "mill", "program"),
    [
        (EXAMPLE_CELL, ORDER, "cnc2", "robot_base_finish_cnc2"),  # DYNALAN blocks
        (TENDING, PlanOrder("A", "bracket", 1), "vf2", "O1001"),  # G-code drip-fed
    ],
    ids=["dyna2400", "iso-cnc"],
)
def test_a_cut_under_way_is_taken_up_as_far_as_it_has_gone(
    tmp_path: Path, cell: Path, order: PlanOrder, mill: str, program: str
) -> None:
    """A running cell's cut, some minutes in: the plan's is that much shorter, and so is
    the whole play; a credit larger than the cut leaves the motion none, and the next
    part's cut on that mill whole."""
    route_index = 1 if mill == "cnc2" else 0
    shift = replace(SHIFT, cell_dir=cell)
    full_s = physical_durations(load_cell(cell)).machining_s[(mill, program)]
    done_s = min(300.0, full_s / 2)

    def play(done_s: float, qty: int, name: str) -> tuple[float, list[float]]:
        at = PartAt(mill, route_index, done_s=done_s)
        taken = replace(order, qty=qty, under_way=(at,))
        run = simulate(replace(shift, orders=(taken,)), tmp_path / name)
        with Journal(run.journal_path) as journal:
            cuts = [
                (s.ended or 0.0) - s.started
                for s in journal.steps()
                if s.kind == "machine" and s.machine == mill
            ]
        finished = run.finished[order.order_id]
        assert finished is not None
        return finished - START, cuts

    whole, whole_cuts = play(0.0, 1, "whole")
    taken, taken_cuts = play(done_s, 1, "taken")
    if mill == "vf2":
        # Drip-fed, the cut is played again from its first byte: its motion is skipped, but
        # a program its line is slower than still takes its line time.
        assert whole_cuts[0] - done_s - 1.0 < taken_cuts[0] < whole_cuts[0]
        return
    # One part: its cut, and the play, end that much sooner.
    assert taken_cuts[0] == pytest.approx(whole_cuts[0] - done_s, abs=1.0)
    assert taken == pytest.approx(whole - done_s, abs=1.0)
    # Two parts, a credit more than the cut's motion: the first cut has none left, and the
    # next part's cut on that mill is whole (what was left is not carried over: the
    # emulated cell's, whatever the mill's kind).
    _, plain_cuts = play(0.0, 2, "plain")
    _, spent_cuts = play(10 * full_s, 2, "spent")
    assert spent_cuts[0] <= taken_cuts[0]
    assert spent_cuts[1] == pytest.approx(plain_cuts[1], abs=0.5)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (
            {"orders": (replace(ORDER, under_way=(PartAt("cnc1", 1, done_s=60.0),)),)},
            "part of A under way: 60 s of a cut done at cnc1, which does not cut it next",
        ),
        (
            {"orders": (replace(ORDER, under_way=(PartAt("cnc1", 0, done_s=-1.0),)),)},
            "part of A under way: -1 s of its cut done: it must be 0 or more",
        ),
        ({"orders": (PlanOrder("A", "wax-robot-arm", 1),)}, "no part type 'wax-robot-arm'"),
        ({"orders": (PlanOrder("A", "wax-robot-base", 0),)}, "quantity must be 1 or more"),
        ({"orders": (PlanOrder("A", "wax-robot-base", 1),) * 2}, "order A is given twice"),
        ({"policy": "random"}, "no scheduler policy 'random'; known: default, downstream-first"),
        ({"until": START}, "must come after its start"),
        ({"faults": (FaultWindow("cnc3", "down", START),)}, "no such machine"),
        (
            {"faults": (FaultWindow("cnc2", "melt", START),)},
            r"'melt' on cnc2: unknown \(known: down",
        ),
        ({"faults": (FaultWindow("plc", "down", START),)}, r"'down' on plc: unknown \(known: drop"),
        (
            {"faults": (FaultWindow("cnc2", "down", START + 10, START + 5),)},
            "must end after it starts",
        ),
        ({"out_of_service": ("lathe",)}, "no machine 'lathe'"),
        ({"held": (HeldPart("X", "wax-robot-base", "shelf"),)}, "no place 'shelf'"),
        ({"held": (HeldPart("X", "wax-robot-base", "robot"),)}, r"no place 'robot' \(the conv"),
        (
            {"orders": (replace(ORDER, under_way=(PartAt("cnc1", 1), PartAt("cnc2", 1))),)},
            "order A: 2 parts under way, more than its quantity 1",
        ),
        (
            {"orders": (replace(ORDER, under_way=(PartAt("shelf"),)),)},
            "part of A under way: no place 'shelf'",
        ),
        (
            {"orders": (replace(ORDER, under_way=(PartAt("cnc2", 3),)),)},
            r"part of A under way: 3 cuts done, but its route has 2 \(0 to 2\)",
        ),
        (
            {
                "orders": (replace(ORDER, under_way=(PartAt("cnc2", 1),)),),
                "held": (HeldPart("X", "wax-robot-base", "cnc2", 1),),
            },
            "part of A under way: cnc2's vise holds held part of X",
        ),
    ],
)
def test_inputs_the_cell_cannot_take_are_refused_before_anything_runs(
    tmp_path: Path, change: dict[str, object], words: str
) -> None:
    inputs = replace(SHIFT, **change)  # type: ignore[arg-type]
    with pytest.raises(UsageError, match=words):
        check_inputs(inputs)
    with pytest.raises(UsageError, match=words):
        simulate(inputs, tmp_path)
    assert not list(tmp_path.iterdir())  # nothing written


def test_without_listed_mills_a_part_is_placed_only_at_a_mill_kind(tmp_path: Path) -> None:
    # The cell's mills by default (no [cell] mills): every machine of a mill kind, never the
    # robot.
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    toml = cell / "cell.toml"
    text = toml.read_text(encoding="utf-8")
    toml.write_text(re.sub(r"(?m)^mills = .*\n", "", text, count=1), encoding="utf-8")
    assert "mills =" not in toml.read_text(encoding="utf-8")
    for place, words in (("robot", "no place 'robot'"), ("cnc2", None)):
        held = HeldPart("X", "wax-robot-base", place, 1)
        inputs = replace(SHIFT, cell_dir=cell, held=(held,))
        if words is None:
            check_inputs(inputs)
        else:
            with pytest.raises(UsageError, match=words):
                check_inputs(inputs)


# -- the scheduler's policies ------------------------------------------------------------------


def _waiting(n: int, part_type: str, seq: int, priority: int = 0) -> PartState:
    return PartState(f"P{n}", part_type, "conveyor", 0, "waiting", priority, seq)


def test_the_policies_choose_the_next_load() -> None:
    types = load_cell(EXAMPLE_CELL).parts
    parts = [
        _waiting(1, "wax-robot-base", 1),
        _waiting(2, "wax-toy-mill-table", 2),
        _waiting(3, "wax-robot-base", 3, priority=5),
    ]
    phys = physical_durations(load_cell(EXAMPLE_CELL))
    work = {
        name: sum(phys.machining_s[(s.mill, s.name)] for s in t.route) for name, t in types.items()
    }
    assert work["wax-toy-mill-table"] < work["wax-robot-base"]

    def load(policy: str, states: list[PartState]) -> str | None:
        transfer = next_transfer(
            states,
            types,
            mills_in_service={"cnc1", "cnc2", "conveyor"},
            pallet_present=True,
            policy=policy,
            work_s=work,
        )
        return None if transfer is None else transfer.part_id

    # Priority first for every policy; then the oldest, or the least machining.
    assert load("downstream-first", parts) == "P3"
    assert load("shortest-first", parts) == "P3"
    assert load("downstream-first", parts[:2]) == "P1"
    assert load("shortest-first", parts[:2]) == "P2"
    # One at a time: nothing is loaded while a part is in the cell.
    at_cnc2 = PartState("P0", "wax-robot-base", "cnc2", 1, "active", 0, 0)
    assert load("downstream-first", [at_cnc2, *parts[:2]]) == "P1"
    assert load("one-at-a-time", [at_cnc2, *parts[:2]]) is None
    assert load("one-at-a-time", parts[:2]) == "P1"


def test_controller_options_carry_the_policy() -> None:
    assert ControllerOptions().policy == "downstream-first"
    assert ControllerOptions(policy="shortest-first").policy == "shortest-first"
    legacy = ControllerOptions(one_at_a_time=True)
    assert (legacy.policy, legacy.one_at_a_time) == ("one-at-a-time", True)
    assert ControllerOptions(policy="one-at-a-time").one_at_a_time is True
    with pytest.raises(UsageError, match="no scheduler policy 'fifo'"):
        ControllerOptions(policy="fifo")


def test_a_plan_looks_less_often_than_the_cell_and_finishes_the_same(tmp_path: Path) -> None:
    """The plan's poll period (PLAN_POLL_S, 15 s) against the cell's own (0.5 s): the same
    steps in the same order, each order finished within seconds of the other (a step's end
    is seen by the step itself; the looks watch idle machines)."""
    orders = (PlanOrder("A", "wax-robot-base", 1), PlanOrder("B", "wax-toy-mill-table", 1))
    down = FaultWindow("cnc2", "down", START + 900, START + 1500)
    inputs = replace(SHIFT, orders=orders, faults=(down,), until=START + 3 * 3600)
    own = simulate(replace(inputs, poll_period=0.0), tmp_path / "own")
    planned = simulate(inputs, tmp_path / "planned")
    assert (own.poll_period, planned.poll_period) == (0.5, PLAN_POLL_S)

    def steps(run: PlanRun) -> list[tuple[str, str, str, str]]:
        with Journal(run.journal_path) as journal:
            return [(s.part_id, s.kind, s.machine, s.state) for s in journal.steps()]

    assert steps(planned) == steps(own)
    for order in orders:
        a, b = own.finished[order.order_id], planned.finished[order.order_id]
        assert a is not None and b is not None, (own.finished, planned.finished)
        assert abs(b - a) <= 10, f"{order.order_id}: {relative(a)} s at 0.5 s, {relative(b)} s"


def test_policies_played_side_by_side_say_what_they_say_one_after_the_other(
    tmp_path: Path,
) -> None:
    """``play(..., workers=3)`` (the command line's, one process a policy) gives the reports
    and chart one process gives: a plan is its inputs' and seed's, not its process's."""
    from cellctl.plan.run import play

    inputs = replace(
        SHIFT,
        orders=(PlanOrder("A", "wax-robot-base", 1), PlanOrder("B", "wax-toy-mill-table", 1)),
        until=START + 1200,
    )
    policies = ("downstream-first", "one-at-a-time", "shortest-first")
    alone = play(inputs, policies, tmp_path / "one", workers=1)
    side = play(inputs, policies, tmp_path / "three", workers=3)

    def figures(report: object) -> dict[str, object]:
        data = dict(report.as_dict())  # type: ignore[attr-defined]
        data.pop("wall_s", None)  # the computer's time, not the plan's
        return data

    assert [figures(r) for r in side.reports] == [figures(r) for r in alone.reports]
    assert [r.policy for r in side.reports] == list(policies)
    assert side.svg == alone.svg
    assert all(r.steps for r in side.reports)
