"""The UR on ``mem://``: a machine's own network interfaces served in one event loop
(:func:`cellctl.emulators.memserve.serve_mem_streams`), the UR driver against its emulator
there on virtual time, and the cobot cell planned (`cellctl plan`) with the same schedule as
its batch run in real time through real sockets."""

from __future__ import annotations

import asyncio
import subprocess
from datetime import datetime
from pathlib import Path

import pytest

from cellctl.cell.config import load_cell
from cellctl.cell.controller import ControllerOptions
from cellctl.cell.journal import Journal, open_journal
from cellctl.emulators.memserve import serve_mem_streams
from cellctl.errors import LinkClosed
from cellctl.kinds.ur.dashboard import RobotMode
from cellctl.kinds.ur.driver import UrOptions, UrRobot
from cellctl.kinds.ur.emulator import MEM_RTDE_HZ, UrEmulator
from cellctl.link import LineSettings, open_link
from cellctl.mailbox import open_mailbox
from cellctl.plan.engine import PlanInputs, PlanOrder, simulate
from cellctl.ui.cell_cli import run_controller

from .conftest import CELLCTL, until
from .test_cell_tending import EXAMPLE, SCALE, tending  # noqa: F401  (tending: the fixture)

LINE = LineSettings.parse("115200,8N1")


@pytest.mark.virtual
async def test_a_stream_handler_serves_each_host_and_sees_it_go() -> None:
    ended: list[str] = []

    async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while line := await reader.readline():
            writer.write(line.upper())
            await writer.drain()
        # The host went away: a write's drain says so, as over TCP.
        writer.write(b"late\n")
        try:
            await writer.drain()
        except ConnectionResetError:
            ended.append("reset")

    listener = serve_mem_streams("echo", LINE, echo)
    try:
        link = await open_link("mem://echo", LINE)
        await link.write(b"hello\n")
        assert await link.read_until(b"\n", timeout=1.0) == b"HELLO\n"
        await link.close()
        await until(lambda: ended == ["reset"], "the handler to see the host go")
        # A second host gets a session of its own; closing the listener cuts it.
        again = await open_link("mem://echo", LINE)
        await again.write(b"x\n")
        assert await again.read_until(b"\n", timeout=1.0) == b"X\n"
        listener.close()
        with pytest.raises(LinkClosed):
            await again.read_until(b"\n", timeout=1.0)
        await again.close()
    finally:
        listener.close()


@pytest.mark.virtual
async def test_the_ur_driver_runs_its_emulator_on_mem_at_the_plans_rtde_rate() -> None:
    emulator = UrEmulator(time_scale=1.0)
    served = await emulator.listen_mem("cobot", LINE)
    assert served.url == "mem://cobot" and served.options == {"rtde_frequency": MEM_RTDE_HZ}
    options = UrOptions(rtde_frequency=MEM_RTDE_HZ)
    robot = await UrRobot.connect(served.url, name="cobot", settings=LINE, options=options)
    try:
        assert (await robot.machine_status()).mode == RobotMode.POWER_OFF
        await robot.initialize()  # power on, brake release: the robot's own seconds
        assert (await robot.machine_status()).mode == RobotMode.RUNNING
        sent = emulator.rtde_sent
        await asyncio.sleep(10.0)
        # Ten seconds of virtual time: RTDE at its rate, give or take the one in flight.
        assert abs(emulator.rtde_sent - sent - 10 * MEM_RTDE_HZ) <= 1
    finally:
        await robot.close()
        await served.close()


def steps_of(journal: Journal) -> tuple[float, list[tuple[str, str, str, str]]]:
    """The makespan (s of the journal's clock) and every step (part, kind, machine, program)
    in the order they started."""
    steps = sorted(journal.steps(), key=lambda s: (s.started, s.id))
    assert steps and all(s.ended is not None for s in steps), "every step ended"
    last = max(s.ended for s in steps if s.ended is not None)
    order = [(s.part_id, s.kind, s.machine, s.program) for s in steps]
    return last - steps[0].started, order


async def test_the_cobot_cell_planned_as_it_runs(
    tending: tuple[object, Path],  # noqa: F811
) -> None:
    _, directory = tending
    with open_mailbox(directory) as mailbox:
        mailbox.post_order("bracket", 2, order_id="A")
    options = ControllerOptions.from_config(load_cell(directory))
    await asyncio.wait_for(
        run_controller(directory, live=False, until_idle=True, options=options), 120
    )
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
    # The same steps in the same order: the plan is the cell's own schedule.
    assert plan_order == real_order
    assert len(plan_order) == 2 * 5  # three transfers and two cuts a part
    print(f"\ncobot cell, 2 brackets: real {real_s * SCALE:.1f} s, plan {plan_s:.1f} s")


def test_cellctl_plan_answers_for_the_cobot_cell(tmp_path: Path) -> None:
    done = subprocess.run(
        [*CELLCTL, "plan", "--dir", str(EXAMPLE), "--add", "bracket:3", "--shift", "3h",
         "--start", "2026-11-27T06:00", "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "3/3" in done.stdout and "bracket" in done.stdout
    assert (tmp_path / "out" / "plan.svg").exists()
