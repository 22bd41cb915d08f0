"""examples/cell-tending end to end: a UR5e tending an iso-cnc mill and a Dyna 2400 with the
PLC, every machine emulated, the real controller running batches. A protective stop in the
middle is alarmed in UR's words; the operator's unlock and release let the batch finish with
no part lost and none cut twice. The batch's plan (on virtual time, the UR on ``mem://``) is
the batch's own schedule."""

from __future__ import annotations

import asyncio
import re
import subprocess
from collections.abc import AsyncIterator
from datetime import datetime
from pathlib import Path

import pytest

from cellctl.cell.config import load_cell
from cellctl.cell.controller import ControllerOptions
from cellctl.cell.journal import Journal, open_journal
from cellctl.emulators.cell import EmulatedCell
from cellctl.errors import UsageError
from cellctl.kinds.ur.dashboard import RuntimeState, SafetyStatus
from cellctl.mailbox import open_mailbox
from cellctl.plan.engine import PlanInputs, PlanOrder, simulate
from cellctl.service.client import attach
from cellctl.testing.rig import write_cell_options
from cellctl.ui.cell_cli import run_controller

from .conftest import CELLCTL, until

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell-tending"
SCALE = 200.0


@pytest.fixture
async def tending(tmp_path: Path) -> AsyncIterator[tuple[EmulatedCell, Path]]:
    cell = EmulatedCell(time_scale=SCALE, template=EXAMPLE)
    directory = tmp_path / "cell"
    await cell.start(directory)
    toml = directory / "cell.toml"
    # A short poll; and the PLC and a look at a machine given the time a loaded box may take
    # (the example's 1 s PLC answer is a LAN's), as the other cells under test have.
    write_cell_options(toml, {"poll_period": 0.1, "read_limit": 2.0}, {}, {"timeout": 5.0})
    try:
        yield cell, directory
    finally:
        await cell.close()


def _cut_once(cell: EmulatedCell, parts: int) -> None:
    """Every physical part on the outfeed, none lost, none cut twice on a mill. (The iso-cnc
    emulator opens a run as its reader starts, its automatic operator's, which may be before
    the part is clamped: such a run names no part, so the Dyna's cuts are counted by part.)"""
    physical = [f"P{n}" for n in range(1, parts + 1)]
    assert sorted(cell.outfeed) == physical, cell.outfeed
    runs = cell.runs_per_part()
    assert {p: r.get("cnc2") for p, r in runs.items()} == dict.fromkeys(physical, 1), runs
    assert all(n == 1 for r in runs.values() for n in r.values()), runs


async def test_a_batch_runs_through_the_cobot_cell(tending: tuple[EmulatedCell, Path]) -> None:
    cell, directory = tending
    with open_mailbox(directory) as mailbox:
        mailbox.post_order("bracket", 2, order_id="A")
    options = ControllerOptions.from_config(load_cell(directory))
    async with asyncio.timeout(120):
        await run_controller(directory, live=False, until_idle=True, options=options)
    with open_journal(directory) as journal:
        done = [(s.machine, s.program) for s in journal.steps() if s.state == "finished"]
    with open_mailbox(directory) as mailbox:
        assert mailbox.get_order("A").state == "done"
    assert sorted(p for m, p in done if m == "robot") == sorted(
        ["conveyor_to_vf2", "vf2_to_cnc2", "cnc2_to_conveyor"] * 2
    )
    _cut_once(cell, 2)
    assert cell.robot.controller.runs.count("conveyor_to_vf2") == 2
    # The plan of the same batch (the UR on mem://, virtual time) is this run's schedule:
    # the same steps in the same order.
    with open_journal(directory) as journal:
        real_s, real_order = steps_of(journal)
    start = datetime(2026, 11, 27, 6, 0).timestamp()
    inputs = PlanInputs(
        cell_dir=EXAMPLE,
        orders=(PlanOrder("A", "bracket", 2),),
        start=start,
        until=start + 8 * 3600,
    )
    run = await asyncio.to_thread(simulate, inputs, directory.parent / "plan")
    assert run.finished["A"] is not None
    with Journal(run.journal_path) as journal:
        plan_s, plan_order = steps_of(journal)
    assert plan_order == real_order
    print(f"\ncobot cell, 2 brackets: real {real_s * SCALE:.1f} s, plan {plan_s:.1f} s")


def steps_of(journal: Journal) -> tuple[float, list[tuple[str, str, str, str]]]:
    """The makespan (s of the journal's clock) and every step (part, kind, machine, program)
    in the order they started."""
    steps = sorted(journal.steps(), key=lambda s: (s.started, s.id))
    assert steps and all(s.ended is not None for s in steps), "every step ended"
    last = max(s.ended for s in steps if s.ended is not None)
    return last - steps[0].started, [(s.part_id, s.kind, s.machine, s.program) for s in steps]


async def test_a_protective_stop_in_the_batch(tending: tuple[EmulatedCell, Path]) -> None:
    cell, directory = tending
    robot = cell.robot.controller
    with open_mailbox(directory) as mailbox:
        mailbox.post_order("bracket", 2, order_id="A")
    stop = asyncio.Event()
    options = ControllerOptions.from_config(load_cell(directory))
    controller = asyncio.ensure_future(
        run_controller(directory, live=False, until_idle=False, options=options, stop=stop)
    )
    try:
        # The second transfer of the batch, mid-way: the arm stops where it is.
        await until(
            lambda: (
                robot.runs.count("vf2_to_cnc2") == 1
                and robot.runtime == RuntimeState.PLAYING
                and robot._move is not None
            ),
            "the robot moving a part from the VF-2 to CNC 2",
        )
        robot.set_fault("protective_stop")
        await until(lambda: (directory / "api.sock").exists(), "the API")
        async with await attach(directory) as api:

            async def alarm_texts() -> list[str]:
                return [a["text"] for a in await api.call("alarms.list", {})]

            async def stopped_alarm() -> bool:
                return any("Safetystatus: PROTECTIVE_STOP" in t for t in await alarm_texts())

            await until(stopped_alarm, "the protective stop's alarm", 30)
            held = [p["id"] for p in await api.call("parts.list", {"statuses": ["held"]})]
            assert len(held) == 1, held  # the part in the gripper, and no other
            # The cell never unlocks it: still stopped while the operator has not acted.
            assert robot.safety == SafetyStatus.PROTECTIVE_STOP
            # The operator: the robot out of automatic service, unlock (UR's 5 s first), play
            # the paused program to its end, back in service, the part released where it is.
            await api.call("machines.out_of_service", {"machine": "robot"})
            # UR refuses an unlock within 5 s of the stop: the operator waits them out.
            await asyncio.sleep(5.0 / SCALE)
            assert (await api.call("robot.unlock", {}))["message"] == "Protective stop releasing"
            await api.call("robot.play", {})
            await until(lambda: robot.runtime == RuntimeState.STOPPED, "the transfer's end")
            await api.call("machines.return_to_service", {"machine": "robot"})
            # Said to be still in the gripper: refused (the cell never takes a part up there).
            with pytest.raises(UsageError, match="cannot be released at 'robot'"):
                await api.call("parts.release", {"id": held[0], "at": "robot"})
            await api.call("parts.release", {"id": held[0], "at": "cnc2"})

            async def order_done() -> bool:
                orders = await api.call("orders.list", {})
                return any(o["id"] == "A" and o["state"] == "done" for o in orders)

            await until(order_done, "order A done", 120)
    finally:
        stop.set()
        async with asyncio.timeout(60):
            await controller
    _cut_once(cell, 2)


def test_demo_runs_a_batch_through_the_cobot_cell(tmp_path: Path) -> None:
    """`cellctl demo --cell examples/cell-tending`: the batch end to end, in a process of its
    own as a user runs it."""
    demo = ["demo", "--cell", str(EXAMPLE), "--parts", "2", "--no-compare", "--time-scale", "200"]
    done = subprocess.run(
        [*CELLCTL, *demo, "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    out = " ".join(done.stdout.split())
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "parts made: 2 x bracket" in out, out[-2000:]
    assert "failed steps: 0" in out, out[-2000:]
    for machine in ("robot", "vf2", "cnc2"):  # each machine of the cell did its share
        used = re.search(rf"utilization {machine}: +([0-9.]+)%", out)
        assert used is not None and float(used.group(1)) > 0, (machine, out[-2000:])
    assert (tmp_path / "cell" / "gantt.svg").is_file()
