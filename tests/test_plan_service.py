"""`plan.run` on a running cell (the emulated cell on real ptys and sockets, its controller
and the control API on a Unix socket): the snapshot of its open orders and machines out of
service, played on a copy while the controller goes on; a viewer may ask, a wrong token may
not; and `cellctl plan` through the API answers the issue's questions."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from cellctl.errors import AccessDenied, MachineInUse, UsageError
from cellctl.plan.run import report_from_dict
from cellctl.service.access import AttachedCell
from cellctl.service.client import RemoteCell, attach
from cellctl.service.server import ApiServer
from cellctl.testing.rig import CellRig
from cellctl.testing.rig import cli as rig_cli


@pytest.fixture
async def running(tmp_path: Path) -> AsyncIterator[tuple[CellRig, ApiServer]]:
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        assert rig.controller is not None
        server = ApiServer(AttachedCell(rig.controller), rig.directory)
        await server.start()
        try:
            yield rig, server
        finally:
            await server.close()


def _hhmm(moment: datetime) -> str:
    return moment.strftime("%H:%M")


async def _viewer(rig: CellRig, server: ApiServer) -> RemoteCell:
    result = await rig.cli("token", "add", "vera", "--role", "viewer")
    assert result.exit_code == 0, result.output
    return await RemoteCell.connect(token=result.output.splitlines()[0].strip(),
                                    socket_path=server.socket_path)  # fmt: skip


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
async def test_a_viewer_plans_the_running_cell_on_a_copy_while_it_runs(
    running: tuple[CellRig, ApiServer],
) -> None:
    rig, server = running
    operator = await attach(rig.directory)
    vera = await _viewer(rig, server)
    try:
        # Orders the cell has not started yet (paused).
        await operator.call("cell.pause", {})
        rig.post("wax-robot-base", 2, "A")
        rig.post("wax-toy-mill-table", 1, "B")
        await rig.wait_for(lambda: rig.order_state("B") == "accepted", "B accepted")
        steps_before = len(rig.journal.steps())
        now = datetime.now()
        fault = (
            f"cnc2:down@{_hhmm(now + timedelta(minutes=2))}-{_hhmm(now + timedelta(minutes=20))}"
        )
        asked = asyncio.create_task(
            vera.call("plan.run", {"shift": "10m", "fault": [fault], "add": ["wax-robot-base:1"]})
        )
        # The API (and the controller behind it) answers while the plan plays.
        status = await vera.call("cell.status", {})
        assert not asked.done() and set(status["machines"]) >= {"robot", "cnc1", "cnc2"}
        with pytest.raises(MachineInUse, match="a plan is being played already"):
            await vera.call("plan.run", {})
        answer = await asked
        # A machine out of service now stays out in the plan: nothing passes cnc1.
        await operator.call("machines.out_of_service", {"machine": "cnc1", "reason": "tool"})
        idle = await vera.call("plan.run", {"shift": "2m"})
    finally:
        await vera.close()
        await operator.close()
    [report] = answer["plan"]["plans"]
    inputs = answer["plan"]["inputs"]
    assert [(o["order_id"], o["qty"]) for o in inputs["orders"]] == [
        ("A", 2),
        ("B", 1),
        ("plan-add1", 1),
    ]
    assert [f["machine"] for f in inputs["faults"]] == ["cnc2"]
    assert report["until"] - report["start"] == 10 * 60
    assert report["down_s"]["cnc2"] > 0
    assert {o["order_id"] for o in report["orders"] if o["finished"] is not None} <= {
        "A", "B", "plan-add1"
    }  # fmt: skip
    assert "<svg" in answer["svg"]
    # Played on a copy: the running cell's journal and orders are as they were.
    assert len(rig.journal.steps()) == steps_before
    assert {o.id for o in rig.mailbox.orders()} == {"A", "B"}
    rig.check_running()
    assert idle["plan"]["inputs"]["out_of_service"] == ["cnc1"]
    [quiet] = idle["plan"]["plans"]
    assert quiet["parts_made"] == {} and quiet["busy_s"]["cnc1"] == 0


async def test_a_wrong_token_is_refused(running: tuple[CellRig, ApiServer]) -> None:
    _, server = running
    with pytest.raises(AccessDenied, match="refused the token"):
        await RemoteCell.connect(token="not-a-token-" + "x" * 30, socket_path=server.socket_path)


async def test_a_bad_fault_argument_is_refused_before_the_plan_plays(
    running: tuple[CellRig, ApiServer],
) -> None:
    """`plan.run` checks each fault's argument as the machine's emulator does, before the
    plan plays: the fault's own words, and the API free for the next plan at once."""
    rig, server = running
    vera = await _viewer(rig, server)
    try:
        rig.post("wax-robot-base", 1, "A")
        for fault, words in (
            ("plc:stuck-door=abc@00:00", "stuck-door needs a mill number 1 or 2, not 'abc'"),
            ("cnc1:noise=zz@00:00", "noise takes RATE"),
        ):
            with pytest.raises(UsageError, match=words):
                await vera.call("plan.run", {"shift": "10m", "fault": [fault]})
    finally:
        await vera.close()


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
async def test_cellctl_plan_through_the_api_answers_the_questions(
    running: tuple[CellRig, ApiServer], tmp_path: Path
) -> None:
    rig, _ = running
    await rig.cli("pause")
    rig.post("wax-robot-base", 2, "A")
    await rig.wait_for(lambda: rig.order_state("A") == "accepted", "A accepted")
    out = tmp_path / "plan-out"
    result = await rig_cli(
        rig.directory, "plan", "--add", "wax-robot-base:1", "--shift", "5m",
        "--policy", "one-at-a-time", "--poll", "2", "--out", str(out),
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    shown = "plan of CIM laboratory machining cell (policy one-at-a-time, seed 0, poll 2 s)"
    assert shown in result.output
    data: dict[str, Any] = json.loads((out / "plan.json").read_text())
    assert json.loads((out / "inputs.json").read_text())["poll_period"] == 2
    for report in data["plans"]:
        added = next(o for o in report["orders"] if o["order_id"] == "plan-add1")
        assert added["qty"] == 1
        assert (added["finished"] is not None) == (added["made"] == 1)
    # The running cell's open order (A, 2 parts) and the one added, played from now.
    assert [(o["order_id"], o["qty"]) for o in data["inputs"]["orders"]] == [
        ("A", 2),
        ("plan-add1", 1),
    ]
    assert all(p["steps"] for p in data["plans"])  # the plan played something
    # Saved beside it: the cell's configuration as the real cell's (the emulation's time
    # scale gone: a plan plays the machines' real times), and the chart.
    saved = (out / "cell" / "cell.toml").read_text()
    assert "time_scale" not in saved and "[machines.cnc1]" in saved
    assert (out / "plan.svg").read_text().startswith("<svg")


async def test_a_part_on_its_way_is_taken_up_where_it_is(
    running: tuple[CellRig, ApiServer],
) -> None:
    rig, _ = running
    rig.post("wax-robot-base", 1, "U")
    client = await attach(rig.directory)
    try:
        # Paused during the rough cut: the cut ends, nothing starts after it.
        await rig.wait_for(lambda: rig.open_steps("machine"), "the rough cut under way")
        await client.call("cell.pause", {})
        await rig.wait_quiet(span=1.0, what="the paused cell at rest")
        [part] = rig.journal.parts(order_id="U")
        assert (part.status, part.location, part.route_index) == ("waiting", "cnc1", 1)
        answer = await client.call("plan.run", {"shift": "1h"})
    finally:
        await client.close()
    [order] = answer["plan"]["inputs"]["orders"]
    assert (order["order_id"], order["qty"]) == ("U", 1)
    # Paused after its cut: none in flight, none of one done.
    assert order["under_way"] == [{"location": "cnc1", "route_index": 1, "done_s": 0.0}]
    [report] = answer["plan"]["plans"]
    assert [(o["order_id"], o["finished"] is not None) for o in report["orders"]] == [("U", True)]
    assert report["under_way_at_start"] == 1
    lines = report_from_dict(report).lines()
    assert "on their way at the start (taken up there): 1" in lines
    # Taken up after its rough cut: the plan neither loads it from the conveyor nor cuts it
    # at cnc1 again; it finishes it at cnc2 and unloads it.
    steps = [(s["kind"], s["machine"], s["program"]) for s in report["steps"]]
    assert ("machine", "cnc1", "robot_base_rough_cnc1") not in steps
    assert not [s for s in steps if s[2] == "conveyor_to_cnc1"]
    assert steps[-2:] == [
        ("machine", "cnc2", "robot_base_finish_cnc2"),
        ("transfer", "robot", "cnc2_to_conveyor"),
    ]


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
async def test_a_part_held_now_stays_held_in_the_plan(running: tuple[CellRig, ApiServer]) -> None:
    rig, _ = running
    rig.post("wax-robot-base", 2, "A")
    await rig.wait_for(lambda: rig.finished_steps("machine") >= 1, "first cut done")
    rig.switch_on("cnc2:stall")  # the finishing cut stalls: its part is held for inspection
    [held] = await rig.wait_for(rig.held_parts, "a part held")
    await rig.cli("pause")
    client = await attach(rig.directory)
    try:
        answer = await client.call("plan.run", {"shift": "3m"})
    finally:
        await client.close()
    inputs = answer["plan"]["inputs"]
    assert inputs["held"] == [
        {
            "order_id": "A",
            "part_type": "wax-robot-base",
            "location": held.location,
            "route_index": held.route_index,
        }
    ]
    # What remains of A is played: its parts less the one held (and any done).
    done = sum(p.status == "done" for p in rig.journal.parts(order_id="A"))
    assert [(o["order_id"], o["qty"]) for o in inputs["orders"]] == [("A", 2 - 1 - done)]
    [report] = answer["plan"]["plans"]
    assert report["held_at_start"] == 1


@pytest.mark.timeout(300)
async def test_a_plan_whose_client_goes_away_ends_its_play(
    running: tuple[CellRig, ApiServer],
) -> None:
    """A month of plan (minutes of CPU) asked, and its client gone a moment later: the play
    ends with it, and the next plan is taken long before the month could have been played."""
    rig, server = running
    vera = await _viewer(rig, server)
    asked = asyncio.create_task(
        vera.call("plan.run", {"shift": "30d", "add": ["wax-robot-base:5000"]})
    )
    operator = await attach(rig.directory)
    try:
        # Playing: a second plan is refused while it plays.
        with pytest.raises(MachineInUse, match="a plan is being played already"):
            await operator.call("plan.run", {"shift": "1m", "add": ["wax-robot-base:1"]})
        await vera.close()
        with contextlib.suppress(Exception):
            await asked
        answer = None
        for _ in range(120):  # the worker killed and reaped: seconds
            try:
                answer = await operator.call(
                    "plan.run", {"shift": "1m", "add": ["wax-robot-base:1"]}
                )
                break
            except MachineInUse as e:
                assert "a plan is being played already" in str(e)
                await asyncio.sleep(0.5)
        assert answer is not None, "the month's play went on after its client left"
        assert answer["plan"]["plans"][0]["until"] - answer["plan"]["plans"][0]["start"] == 60
    finally:
        await operator.close()
