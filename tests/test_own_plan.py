"""A cell's plan of its own open work (``[mailbox] plan_period``): what
:func:`cellctl.service.planning.own_plan` says of the example cell played on virtual time, and
the bridge planning again when its orders change and putting the plan in its state message
(the broker and the factory: tests/test_factory_plan_dispatch.py)."""

from __future__ import annotations

import asyncio
import shutil
from pathlib import Path

from cellctl.cell.commands import OPERATOR_OUT
from cellctl.cell.config import load_cell
from cellctl.cell.journal import open_journal
from cellctl.mailbox import open_mailbox
from cellctl.mailbox.mqtt import MqttBridge, MqttSettings, PlanEstimate
from cellctl.mailbox.wire import StateMessage
from cellctl.service.planning import OWN_PLAN_DIR, own_plan
from tests.test_factory_units import EXAMPLE, RunningCell

#: Seconds of the machines' time a plan plays at most here: a part whose first machine is out
#: of service does not finish within it.
HORIZON_S = 120.0
WAIT_S = 60.0


def example_cell(tmp_path: Path, time_scale: float | None = None) -> Path:
    cell_dir = tmp_path / "cell"
    shutil.copytree(EXAMPLE, cell_dir)
    if time_scale is not None:
        toml = cell_dir / "cell.toml"
        text = toml.read_text(encoding="utf-8")
        toml.write_text(text.replace("[cell]\n", f"[cell]\ntime_scale = {time_scale}\n", 1))
    return cell_dir


async def test_nothing_open_is_done_now_and_a_machine_out_holds_work_to_the_horizon(
    tmp_path: Path,
) -> None:
    cell_dir = example_cell(tmp_path, time_scale=10)
    with open_mailbox(cell_dir) as mailbox, open_journal(cell_dir) as journal:
        idle = await own_plan(cell_dir, mailbox, journal, HORIZON_S)
        assert idle.finish_s == 0.0
        mailbox.post_order("wax-robot-base", 1, 0, order_id="A")
        journal.set_machine_service("cnc1", False, f"{OPERATOR_OUT}: repair")
        stuck = await own_plan(cell_dir, mailbox, journal, HORIZON_S)
    # The plan plays the real machines' times; the emulated cell runs ten times faster.
    assert stuck.finish_s == HORIZON_S / 10
    assert stuck.planned_at >= idle.planned_at
    assert not (cell_dir / OWN_PLAN_DIR).exists()  # its play is not left behind


async def test_the_bridge_plans_again_when_its_orders_change_and_says_so_in_its_state(
    tmp_path: Path,
) -> None:
    cell_dir = example_cell(tmp_path)
    (cell_dir / "mqtt.toml").write_text('username = "cell1"\npassword = "x"\n')
    (cell_dir / "mqtt.toml").chmod(0o600)
    settings = MqttSettings.load("mqtt://127.0.0.1:1/cellctl/cell1", cell_dir / "mqtt.toml")
    plans: list[PlanEstimate] = []
    planned = asyncio.Event()
    with open_mailbox(cell_dir) as mailbox, open_journal(cell_dir) as journal:
        journal.set_machine_service("cnc1", False, f"{OPERATOR_OUT}: repair")

        async def planner() -> PlanEstimate:
            plans.append(await own_plan(cell_dir, mailbox, journal, HORIZON_S))
            planned.set()  # the bridge takes it before the test's task runs again
            return plans[-1]

        cell = RunningCell(load_cell(cell_dir))
        bridge = MqttBridge(settings, cell, mailbox, journal, planner=planner, plan_period=3600)
        # Before any plan: the state without plan fields, as a cell that does not plan.
        assert "plan_finish_s" not in bridge.state()
        loop = asyncio.create_task(bridge._plan_loop(planner))
        try:
            await next_plan(planned)  # the first: nothing open
            assert bridge.state()["plan_finish_s"] == 0.0
            mailbox.post_order("wax-robot-base", 1, 0, order_id="A")
            await next_plan(planned)  # again at once: an order came (the period is an hour)
            assert len(plans) == 2
            state = bridge.state()
            assert state["plan_finish_s"] == HORIZON_S
            assert state["planned_at"] == round(plans[-1].planned_at, 3)
            message = StateMessage(**state, time=plans[-1].planned_at)
            assert '"plan_finish_s":120.0' in message.model_dump_json(exclude_none=True)
        finally:
            loop.cancel()
            await asyncio.gather(loop, return_exceptions=True)


async def next_plan(planned: asyncio.Event) -> None:
    async with asyncio.timeout(WAIT_S):
        await planned.wait()
    planned.clear()
