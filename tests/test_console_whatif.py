"""The console's WHAT IF (CELL menu, 9): a plan of the running cell through the control API's
``plan.run``, asked by a viewer with a form, shown as the plan's report and a text Gantt
chart; input refused in the parser's words (in the form) and in the API's (the form again).

The cell is the emulated one on real ptys and sockets, its controller and API in this
process; the console is driven with Textual's Pilot at 80x24.
"""

from __future__ import annotations

import re
from collections.abc import AsyncIterator
from datetime import datetime, timedelta
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.errors import UsageError
from cellctl.plan.engine import FaultWindow
from cellctl.plan.report import PlanReport
from cellctl.service.access import AttachedCell
from cellctl.service.client import RemoteCell
from cellctl.service.server import ApiServer
from cellctl.testing.rig import CellRig
from cellctl.ui.console.app import ConsoleApp
from cellctl.ui.console.dialogs import FieldRefused
from cellctl.ui.console.whatif import (
    FAULT,
    GANTT_WIDTH,
    IDLE,
    LINE_WIDTH,
    fitted,
    gantt_lines,
    plan_params,
    refusal_field,
)
from tests.test_console import SIZE, fill, screen_text, type_text, wait_text

#: A Gantt row on the screen: the machine, then one character per slot between bars.
GANTT_ROW = re.compile(rf"^\s*(robot|cnc1|cnc2)\s*\|([^|]{{{GANTT_WIDTH}}})\|", re.MULTILINE)


@pytest.fixture
async def viewer(tmp_path: Any) -> AsyncIterator[tuple[CellRig, RemoteCell]]:
    """A running cell (controller and API in this process) and a client with a viewer's
    token: what a planner who may not act on the cell has."""
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        assert rig.controller is not None
        server = ApiServer(AttachedCell(rig.controller), rig.directory)
        await server.start()
        result = await rig.cli("token", "add", "vera", "--role", "viewer")
        assert result.exit_code == 0, result.output
        token = result.output.splitlines()[0].strip()
        client = await RemoteCell.connect(token=token, socket_path=server.socket_path)
        try:
            yield rig, client
        finally:
            await client.close()
            await server.close()


def _hhmm(moment: datetime) -> str:
    return moment.strftime("%H:%M")


@pytest.mark.timeout(300)  # the plan plays on a busy box: CPU, not waiting
async def test_a_viewer_plans_ahead_in_the_console(viewer: tuple[CellRig, RemoteCell]) -> None:
    rig, client = viewer
    steps_before = len(rig.journal.steps())
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "attached to cellctl run (pid")
        await pilot.press("c")
        shown = await wait_text(pilot, "9. WHAT IF")
        assert "8. EXIT" in shown and "7. EMERGENCY STOP" in shown  # the numbers kept
        await pilot.press("9")
        await wait_text(pilot, "WHAT IF", "Horizon:")
        now = datetime.now()
        # Two minutes ahead: the plan (which starts when the API is asked) still has it.
        down = f"cnc2:down@{_hhmm(now + timedelta(minutes=2))}-{_hhmm(now + timedelta(minutes=4))}"
        # Three parts in an hour, looked at every 2 s: a plan that plays for some seconds
        # (the default poll plays it in well under one), to see the console live meanwhile.
        await fill(pilot, "#horizon", "1h")
        await fill(pilot, "#poll", "2")
        await fill(pilot, "#fault", down)
        await fill(pilot, "#add", "wax-robot-base:3")
        await pilot.press("enter")
        await wait_text(pilot, "planning...")
        # The console stays live while the plan plays: the menu answers a key.
        await pilot.press("escape")
        await wait_text(pilot, "MAIN MENU")
        shown = await wait_text(pilot, "Gantt chart, policy downstream-first", timeout=240)
        # The header, broken after a comma to fit the 78 columns.
        header = "plan of CIM laboratory machining cell (policy downstream-first, seed 0,"
        assert header in shown and "poll 2 s)" in shown, shown
        assert f"fault: cnc2 down from {(now + timedelta(minutes=2)):%a %H:%M}:00" in shown
        # The added order's row: its part type, parts made of three, and its verdict.
        row = next(line for line in shown.splitlines() if "plan-add1" in line)
        assert "wax-robot-base" in row and "/3" in row
        assert any(v in row for v in ("on time", "late", "finished", "not finished"))
        rows = dict(GANTT_ROW.findall(shown))
        assert set(rows) == {"robot", "cnc1", "cnc2"}
        # The part's first transfer and cut, letter A (its type); cnc2 idle in its window.
        assert "A" in rows["robot"] and "A" in rows["cnc1"]
        assert FAULT in rows["cnc2"] and set(rows["cnc2"]) <= {FAULT, IDLE, "A"}
        assert "one character = 0:01:00: A wax-robot-base" in shown
        assert "order     part type           made finishes     due          verdict" in shown
        await pilot.press("enter")  # closes the view
        shown = await wait_text(pilot, "plan (downstream-first): on time")
        assert "Gantt chart" not in shown
    # Played on a copy: nothing of the running cell was written.
    assert len(rig.journal.steps()) == steps_before
    assert not rig.mailbox.orders()
    rig.check_running()


@pytest.mark.timeout(120)
async def test_input_refused_in_the_parsers_and_the_apis_words(
    viewer: tuple[CellRig, RemoteCell],
) -> None:
    rig, client = viewer
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "attached to cellctl run (pid")
        await pilot.press("c", "9")
        await wait_text(pilot, "Horizon:")
        await fill(pilot, "#horizon", "8x")
        await pilot.press("enter")
        await wait_text(pilot, "duration '8x': write a number and a unit")
        await fill(pilot, "#horizon", "2m")
        await fill(pilot, "#add", "wax-robot-base:0")
        await pilot.press("enter")
        await wait_text(pilot, "--add 'wax-robot-base:0': the quantity must be 1 to")
        # Past the parsers, the API refuses what the cell does not have: the form again,
        # its answers kept, the API's words in it.
        await fill(pilot, "#add", "wax-robot-base:1")
        # A window well inside the horizon (now + 1 min, cut to the minute, could fall before
        # the plan's start, and be refused as a window after its end instead).
        await fill(pilot, "#horizon", "10m")
        await fill(pilot, "#fault", f"cnc9:down@{_hhmm(datetime.now() + timedelta(minutes=3))}")
        await pilot.press("enter")
        shown = await wait_text(pilot, "the cell has no such machine (known: robot, cnc1, cnc2")
        assert "Horizon:" in shown
        assert app.screen.query_one("#add").value == "wax-robot-base:1"  # type: ignore[attr-defined]
        await pilot.press("escape")
        shown = await wait_text(pilot, "no plan")
        assert "Gantt chart" not in screen_text(app)
    assert not rig.mailbox.orders()


def _good_answers() -> dict[str, str]:
    now = datetime.now()
    down = f"cnc2:down@{_hhmm(now + timedelta(minutes=2))}-{_hhmm(now + timedelta(minutes=4))}"
    return {"horizon": "2h", "fault": down, "add": "wax-robot-base:2", "policy": "default",
            "poll": "", "seed": ""}  # fmt: skip


#: Per field, a refused answer (by the parsers, or past them by the API), the first words of
#: the refusal, and what the operator types next ("": Backspace, the field emptied).
REFUSED = [
    ("horizon", "8x", "duration '8x': write a number", "2h"),
    ("horizon", "25:00", "time '25:00': hours 0-23", "3h"),
    ("fault", "cnc2:down", "--fault 'cnc2:down': write MACHINE", ""),
    ("fault", "cnc9:down@{soon}", "fault on 'cnc9': the cell has no such machine", ""),  # API
    ("add", "wax-robot-base:0", "--add 'wax-robot-base:0': the quantity", ""),
    ("add", "no-such-part:1", "order plan-add1: the cell makes no 'no-such-part'", ""),  # API
    ("policy", "all,default", "--policy 'all,default': all plays every", "all"),
    ("policy", "bogus", "policy 'bogus': unknown (known:", "all"),  # API
    ("poll", "0", "poll '0': seconds", "5"),
    ("seed", "-1", "--seed '-1': a whole number", "7"),
]


@pytest.mark.timeout(300)
async def test_a_refusal_selects_the_field_it_names(viewer: tuple[CellRig, RemoteCell]) -> None:
    """Whatever field is refused, in the parsers' words or the API's, that field's text is
    selected: what the operator types next replaces it, and every other answer stays."""
    rig, client = viewer
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "attached to cellctl run (pid")
        await pilot.press("c", "9")
        await wait_text(pilot, "Horizon:", "Seed:")
        for field, bad, words, typed in REFUSED:
            soon = _hhmm(datetime.now() + timedelta(minutes=2))
            answers = _good_answers() | {field: bad.format(soon=soon)}
            for key, value in answers.items():
                await fill(pilot, f"#{key}", value)
            await pilot.press("enter")
            await wait_text(pilot, words)
            await (type_text(pilot, typed) if typed else pilot.press("backspace"))
            shown = {key: app.screen.query_one(f"#{key}").value for key in answers}  # type: ignore[attr-defined]
            assert shown == answers | {field: typed}, (field, bad, screen_text(app))
        await pilot.press("escape")
        await wait_text(pilot, "no plan")
    assert not rig.mailbox.orders()


@pytest.mark.timeout(120)
async def test_each_refusal_of_the_api_names_its_field(
    viewer: tuple[CellRig, RemoteCell],
) -> None:
    """The API's own refusals of ``plan.run`` (its checks of the cell, its parameters'
    schema) are read as refusals of the form's fields: the form selects that one."""
    _, client = viewer
    soon = _hhmm(datetime.now() + timedelta(minutes=2))
    calls = [
        ({"shift": "8x"}, "horizon"),
        ({"until": "25:00"}, "horizon"),
        ({"shift": "1" * 41}, "horizon"),  # the schema's
        ({"fault": [f"cnc9:down@{soon}"]}, "fault"),
        ({"fault": [f"cnc1:no-such-switch@{soon}"]}, "fault"),
        ({"add": ["no-such-part:1"]}, "add"),
        ({"add": []}, "add"),  # nothing to plan: no open orders
        ({"add": ["x" * 201]}, "add"),  # the schema's
        ({"policy": "bogus"}, "policy"),
        ({"poll": 0}, "poll"),
        ({"poll": "fast"}, "poll"),
        ({"poll": [5]}, "poll"),
        ({"seed": -1}, "seed"),
    ]
    said = {}
    for params, field in calls:
        with pytest.raises(UsageError) as refused:
            await client.call("plan.run", {"shift": "2m", "add": ["wax-robot-base:1"]} | params)
        assert refusal_field(str(refused.value)) == field, (params, str(refused.value))
        said[repr(params)] = str(refused.value)
    # The poll refused in the words of the console's form and of `cellctl plan --poll`.
    assert said["{'poll': 0}"].endswith("poll 0: seconds, more than 0 and at most 600"), said


def _report(steps: list[dict[str, Any]], faults: list[FaultWindow]) -> PlanReport:
    return PlanReport(
        cell="c", policy="default", seed=0, start=1000.0, until=1600.0, ended=1600.0,
        wall_s=0.0, orders=[], parts_made={}, busy_s={}, down_s={},
        utilization={"robot": 0.0, "cnc1": 0.0, "cnc2": 0.0}, faults=faults, steps=steps,
    )  # fmt: skip


def _step(machine: str, part_type: str, a: float, b: float, state: str = "finished") -> Any:
    return {"machine": machine, "part_type": part_type, "started": a, "ended": b, "state": state}


def test_the_gantt_rows_put_each_step_in_its_slots() -> None:
    # 600 s over 60 characters: 10 s a character.
    report = _report(
        [
            _step("robot", "base", 1000, 1020),
            _step("cnc1", "base", 1020, 1300),
            _step("cnc1", "table", 1300, 1400, "failed"),
            _step("robot", "table", 1500, 1510),
        ],
        [FaultWindow("cnc2", "down", 1100, 1200)],
    )
    lines = gantt_lines(report)
    rows = dict(GANTT_ROW.findall("\n".join(lines)))
    assert rows["robot"] == "AA" + "." * 48 + "B" + "." * 9
    assert rows["cnc1"] == "." * 2 + "A" * 28 + "!" * 10 + "." * 20
    assert rows["cnc2"] == "." * 10 + "x" * 10 + "." * 40
    legend = " ".join(lines[4:])
    assert legend == (
        "one character = 10.0 s: A base, B table, ! failed step, x fault window, . idle"
    )
    assert all(len(line) <= 78 for line in lines)


@settings(max_examples=200, deadline=None)
@given(
    st.fixed_dictionaries(
        {k: st.text(max_size=60) for k in ("horizon", "fault", "add", "policy", "poll", "seed")}
    )
)
def test_any_form_answer_is_params_or_a_usage_error(raw: dict[str, str]) -> None:
    """Params, or a refusal in words that names one of the form's fields (the one the form
    selects)."""
    try:
        params = plan_params(raw, 1_795_600_000.0)
    except UsageError as e:
        assert str(e)
        assert isinstance(e, FieldRefused) and e.field in raw
        return
    keys = set(params) - {"poll", "seed"}
    assert keys == {"shift", "add", "fault", "policy"} or "until" in keys
    assert 0 < params.get("poll", 1) <= 600
    assert 0 <= params.get("seed", 0) < 2**63


def test_a_long_line_of_the_plan_goes_on_under_itself() -> None:
    header = "plan of CIM laboratory machining cell (policy downstream-first, seed 0, poll 5 s)"
    assert fitted([header]) == [
        "plan of CIM laboratory machining cell (policy downstream-first, seed 0,",
        "    poll 5 s)",
    ]
    # Every word kept, in its order; a word longer than a line cut; every line in the view.
    words = "utilization: " + ", ".join(f"machine{i} 12.5%" for i in range(12))
    lines = fitted([words])
    assert len(lines) > 1 and " ".join(lines).split() == words.split()
    assert "".join(line.strip() for line in fitted(["x" * 200])) == "x" * 200
    assert all(len(line) <= LINE_WIDTH for line in fitted([words, "x" * 200, "short"]))
    assert fitted(["short"]) == ["short"]


def test_the_forms_poll_is_the_plans_own() -> None:
    """Empty: the plan's default (no ``poll`` sent); seconds as ``cellctl plan --poll``."""
    base = {"horizon": "8h", "add": "wax-robot-base:1"}
    assert "poll" not in plan_params(base, 1_795_600_000.0)
    assert plan_params(base | {"poll": " 0.5 "}, 1_795_600_000.0)["poll"] == 0.5
    for bad in ("0", "-1", "nan", "inf", "5s", "601"):
        with pytest.raises(UsageError, match=r"poll .*more than 0 and at most 600"):
            plan_params(base | {"poll": bad}, 1_795_600_000.0)
