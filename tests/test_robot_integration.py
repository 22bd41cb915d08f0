"""The robot driver against the robot emulator over real ptys, TCP, RFC 2217 and ser2net."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from cellctl.drivers.state import StateStore
from cellctl.emulators.serve import serve
from cellctl.errors import ChecksumError, DeviceError, LinkClosed, LinkError, LinkTimeout
from cellctl.kinds.ibm7545.aml import compile_source
from cellctl.kinds.ibm7545.driver import Ibm7545Robot, RobotConfig, RobotHalted
from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator
from cellctl.kinds.ibm7545.records import ProgramFile
from cellctl.link import ROBOT_LINE

from .conftest import Ser2net, Served

EXAMPLES = Path(__file__).parent.parent / "examples" / "robot"

SHORT = """
-- pick a part and put it back
PMOVE(PT(300, 100, 0, 0))
DOWN
GRASP
UP
WRITEO(3, 1)
PMOVE(PT(350, -50, 0, 90))
RELEASE
END
"""

OUT_OF_REACH = """
PMOVE(PT(2000, 0, 0, 0))
END
"""

WAITS = """
WAITI(5, 1)
WRITEO(7, 1)
END
"""


def program(text: str, name: str = "TEST") -> ProgramFile:
    return compile_source(text, name, 1)


async def connect(served: Served, **config: float) -> Ibm7545Robot:
    return await Ibm7545Robot.connect(
        served.url, name="robot1", config=RobotConfig(**config) if config else None
    )


async def wait_runs(emulator: Ibm7545Emulator, count: int, robot: Ibm7545Robot) -> None:
    """Poll the controller (as a host does) until the emulator logged ``count`` finished runs."""
    loop = robot.link._loop
    deadline = loop.time() + 10
    while sum(r.end is not None for r in emulator.runs) < count:
        assert loop.time() < deadline, "program did not finish"
        await robot.machine_status()


async def test_full_session_every_function(robot_served: Served) -> None:
    robot = await connect(robot_served)
    async with robot:
        await robot.initialize()
        assert robot.state == 1
        await robot.download(2, program(SHORT))
        assert robot.partitions[2] == "TEST"
        await robot.go(2)
        assert robot.state == 2
        await wait_runs(robot_served.emulator, 1, robot)
        assert robot_served.emulator.runs[0].outcome == "completed"
        dido = await robot.io()
        assert dido.output(3)
        status = await robot.status()
        assert status.machine.ok and status.partitions[2] == "TEST"
        assert await robot.reject_status() == (0, "no reject status")
        await robot.stop()
        assert robot.state == 1
        await robot.return_home()
        await robot.reset_errors()
        await robot.halt()
        assert robot.state == 0 and not any(robot.partitions.values())


async def test_example_transfer_programs_compile_and_download(robot_served: Served) -> None:
    robot = await connect(robot_served)
    async with robot:
        await robot.initialize()
        for partition, source in enumerate(sorted(EXAMPLES.glob("*.aml")), start=1):
            prog = compile_source(source.read_text(), source.stem[:8].upper(), partition)
            await robot.download(partition, prog)
            assert robot.holds(partition, prog)


async def test_go_before_initialize_is_improper_startup_sequence(robot_served: Served) -> None:
    robot = await connect(robot_served)
    async with robot:
        with pytest.raises(DeviceError) as err:
            await robot.download(1, program(SHORT))
    assert err.value.code == 48 and "improper startup sequence" in str(err.value)


async def test_go_on_empty_partition_says_partition_empty(robot_served: Served) -> None:
    robot = await connect(robot_served)
    async with robot:
        await robot.initialize()
        with pytest.raises(DeviceError, match="partition empty") as err:
            await robot.go(4)
    assert err.value.code == 3  # the host's state says so: nothing goes out


async def test_point_out_of_workspace_shows_in_status(robot_served: Served) -> None:
    robot = await connect(robot_served)
    async with robot:
        await robot.initialize()
        await robot.download(1, program(OUT_OF_REACH))
        await robot.go(1)
        await wait_runs(robot_served.emulator, 1, robot)
        status = await robot.status()
    assert "point out of workspace" in str(status.machine)
    assert robot_served.emulator.runs[0].outcome != "completed"


async def test_waiti_blocks_until_the_input_is_set(robot_served: Served) -> None:
    robot = await connect(robot_served)
    async with robot:
        await robot.initialize()
        await robot.download(1, program(WAITS))
        await robot.go(1)
        for _ in range(5):
            assert not (await robot.io()).output(7)
        robot_served.emulator.set_input(5, True)
        await wait_runs(robot_served.emulator, 1, robot)
        assert (await robot.io()).output(7)


async def test_host_state_survives_restart_and_is_per_robot(
    robot_served: Served, tmp_path: Path
) -> None:
    store = StateStore(tmp_path)
    async with await Ibm7545Robot.connect(robot_served.url, name="r1", store=store) as robot:
        await robot.initialize()
        await robot.download(5, program(SHORT))
    async with await Ibm7545Robot.connect(robot_served.url, name="r1", store=store) as again:
        assert again.state == 1 and again.partitions[5] == "TEST"
    async with await Ibm7545Robot.connect(robot_served.url, name="r2", store=store) as other:
        assert other.state == 0 and other.partitions[5] is None


# -- fault switches -------------------------------------------------------------------------------


async def test_fault_power_off(robot_served: Served) -> None:
    robot_served.emulator.set_fault("power-off")
    async with await connect(robot_served) as robot:
        with pytest.raises(DeviceError, match="manipulator power off") as err:
            await robot.initialize()
    assert err.value.code == 128


async def test_fault_servo_error(robot_served: Served) -> None:
    robot_served.emulator.set_fault("servo-error")
    async with await connect(robot_served) as robot:
        status = await robot.status()
        assert "servo error" in str(status.machine)
        with pytest.raises(DeviceError):
            await robot.initialize()
        robot_served.emulator.clear_fault("servo-error")
        await robot.reset_errors()
        await robot.initialize()
        assert (await robot.status()).machine.ok


async def test_fault_corrupt_checksum_retried(robot_served: Served) -> None:
    robot_served.emulator.set_fault("corrupt-checksum", "2")
    async with await connect(robot_served) as robot:
        status = await robot.status()
    assert status.machine.ok
    assert robot.counters.checksum_retries == 2


async def test_fault_corrupt_checksum_beyond_retries_raises(robot_served: Served) -> None:
    robot_served.emulator.set_fault("corrupt-checksum", "10")
    async with await connect(robot_served, checksum_retries=2) as robot:
        with pytest.raises(ChecksumError) as err:
            await robot.status()
    assert err.value.raw.startswith(b"D02")


async def test_fault_drop_closes_the_link(robot_served: Served) -> None:
    robot_served.emulator.set_fault("drop")
    async with await connect(robot_served, reply_timeout=1.0) as robot:
        with pytest.raises(LinkError) as err:
            await robot.status()
    # A pty that is dropped can only look silent to the host; sockets see the close.
    assert isinstance(err.value, LinkClosed | LinkTimeout)


async def test_fault_silent_raises_link_timeout(robot_served: Served) -> None:
    robot_served.emulator.set_fault("silent")
    async with await connect(robot_served, reply_timeout=0.2) as robot:
        with pytest.raises(LinkTimeout, match="no answer"):
            await robot.status()


async def test_reconnect_after_drop_works_on_sockets() -> None:
    emulator = Ibm7545Emulator(time_scale=200.0)
    server = await serve(emulator, "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    try:
        emulator.set_fault("drop")
        async with await Ibm7545Robot.connect(server.url) as robot:
            with pytest.raises(LinkError):
                await robot.status()
        emulator.clear_fault("drop")
        async with await Ibm7545Robot.connect(server.url) as robot:
            assert (await robot.status()).machine.ok
    finally:
        await server.close()


# -- through a real ser2net ---------------------------------------------------------------------


async def test_through_real_ser2net_rfc2217(ser2net_available: None, tmp_path: Path) -> None:
    emulator = Ibm7545Emulator(time_scale=200.0)
    server = await serve(emulator, "pty", ROBOT_LINE, pacing=False)
    proxy = Ser2net(server.url, "4800e72", tmp_path)
    try:
        await proxy.wait_listening()
        async with await Ibm7545Robot.connect(proxy.url, name="robot1") as robot:
            await robot.initialize()
            await robot.download(3, program(SHORT))
            await robot.go(3)
            await wait_runs(emulator, 1, robot)
            assert (await robot.io()).output(3)
            assert robot.link.has_modem_lines
    finally:
        proxy.stop()
        await server.close()
    assert [r.outcome for r in emulator.runs] == ["completed"]


async def test_wait_cycle_end_sees_the_done_output(robot_served: Served) -> None:
    done = "WRITEO(6, 0)\nPMOVE(PT(300, 0, 0, 0))\nWRITEO(6, 1)\nEND\n"
    async with await connect(robot_served) as robot:
        await robot.initialize()
        await robot.download(1, program(done))
        await robot.go(1)
        assert robot.state == 2
        await robot.wait_cycle_end(6, timeout=10, poll=0.01)
        assert robot.state == 1
        with pytest.raises(LinkTimeout, match="output 7 did not go 1"):
            await robot.wait_output(7, True, timeout=0.05, poll=0.01)


async def test_wait_cycle_end_is_cut_short_by_a_servo_error(robot_served: Served) -> None:
    """The cycle waits for input 5 (it never comes); a servo error aborts it, and the wait
    says so at its next poll instead of running out its timeout."""
    async with await connect(robot_served) as robot:
        await robot.initialize()
        await robot.download(1, program(WAITS))
        await robot.go(1)
        waiting = asyncio.ensure_future(robot.wait_cycle_end(7, timeout=30, poll=0.01))
        await asyncio.sleep(0.1)
        assert not waiting.done()
        robot_served.emulator.set_fault("servo-error")
        async with asyncio.timeout(5):
            with pytest.raises(RobotHalted, match="servo error") as caught:
                await waiting
        assert caught.value.status.flags & 128
        assert robot.state == 0  # the controller needs INIT again
        assert robot_served.emulator.onsets.get("servo-error") is not None
