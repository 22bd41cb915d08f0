"""The UR on ``mem://``: a machine's own network interfaces served in one event loop
(:func:`cellctl.emulators.memserve.serve_mem_streams`), the UR driver against its emulator
there on virtual time, and `cellctl plan` of the cobot cell. (Its plan against its batch in
real time: tests/test_cell_tending.py.)"""

from __future__ import annotations

import asyncio
import subprocess
from pathlib import Path

import pytest

from cellctl.emulators.memserve import serve_mem_streams
from cellctl.errors import LinkClosed
from cellctl.kinds.ur.dashboard import RobotMode
from cellctl.kinds.ur.driver import UrOptions, UrRobot
from cellctl.kinds.ur.emulator import MEM_RTDE_HZ, UrEmulator
from cellctl.link import LineSettings, open_link

from .conftest import CELLCTL, until
from .test_cell_tending import EXAMPLE

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


def test_cellctl_plan_answers_for_the_cobot_cell(tmp_path: Path) -> None:
    done = subprocess.run(
        [*CELLCTL, "plan", "--dir", str(EXAMPLE), "--add", "bracket:3", "--shift", "3h",
         "--start", "2026-11-27T06:00", "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "3/3" in done.stdout and "bracket" in done.stdout
    assert (tmp_path / "out" / "plan.svg").exists()
