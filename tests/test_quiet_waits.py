"""A wait that knows how long the machine takes: a robot's cycle end left unasked until its
least time -- fewer exchanges on the line, the same outcome. Over ``mem://`` on virtual time
(the machines' own times, the robot's own 4800-baud line), counted in exchanges.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import pytest

from cellctl.clock import current_clock, run_virtual
from cellctl.emulators.memserve import serve_mem
from cellctl.kinds.ibm7545.aml import compile_source
from cellctl.kinds.ibm7545.driver import Ibm7545Robot, RobotHalted
from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator
from cellctl.link import ROBOT_LINE, TrafficLog
from cellctl.link.trace import SENT
from cellctl.testing.rig import CellRig

# A cycle of several seconds on the arm's model, its "cycle done" output raised at the end.
CYCLE = """
WRITEO(6, 0)
PMOVE(PT(300, 100, 0, 0))
PMOVE(PT(350, -200, 0, 90))
PMOVE(PT(300, 100, 0, 0))
PMOVE(PT(350, -200, 0, 90))
WRITEO(6, 1)
END
"""
DIDO_READ = b"10\r\n"  # the operand record of R 10 (DI/DO)


def _dido_reads(trace: TrafficLog) -> list[float]:
    """When the host asked for DI/DO (its R 10 operand records), wall time."""
    return [at for at, _, way, data in trace.entries if way == SENT and data == DIDO_READ]


async def _cycle(robot: Ibm7545Robot, quiet: float) -> tuple[float, int]:
    """One run of CYCLE: how long until its end was seen, and the transactions it took."""
    clock = current_clock()
    await robot.go(1)
    before = robot.counters.transactions
    started = clock.monotonic()
    await robot.wait_cycle_end(6, timeout=60, poll=0.002, watch_every=0.25, quiet=quiet)
    return clock.monotonic() - started, robot.counters.transactions - before


def test_a_cycle_left_unasked_until_its_least_time_ends_as_seen_polled() -> None:
    async def session() -> None:
        clock = current_clock()
        server = await serve_mem(Ibm7545Emulator(), ROBOT_LINE)
        trace = TrafficLog(None, keep=100_000)
        robot = await Ibm7545Robot.connect(server.url, name="robot1", trace=trace)
        try:
            await robot.initialize()
            await robot.download(1, compile_source(CYCLE, "CYCLE", 1))
            await _cycle(robot, 0.0)  # from home; the runs below start where it ended
            polled, polled_n = await _cycle(robot, 0.0)
            assert polled > 2.0  # a cycle of seconds, polled from its start
            asked = clock.now()
            quiet = 0.9 * polled
            seen, quiet_n = await _cycle(robot, quiet)
            assert robot.state == 1
            # The end is seen as the polled wait saw it (within one read of the line), with
            # a fraction of the exchanges.
            assert seen == pytest.approx(polled, abs=0.1)
            assert quiet_n * 2 < polled_n
            first = min(at for at in _dido_reads(trace) if at > asked)
            assert first >= asked + quiet
        finally:
            await robot.close()
            await server.close()

    run_virtual(session())


@asynccontextmanager
async def running(emulator: Ibm7545Emulator, source: str) -> AsyncIterator[Ibm7545Robot]:
    """A driver over ``mem://`` to ``emulator``, initialized, running AML ``source`` from
    partition 1 (closed after)."""
    server = await serve_mem(emulator, ROBOT_LINE)
    robot = await Ibm7545Robot.connect(server.url, name="robot1")
    try:
        await robot.initialize()
        await robot.download(1, compile_source(source, "CYCLE", 1))
        await robot.go(1)
        yield robot
    finally:
        await robot.close()
        await server.close()


def test_a_servo_error_while_the_end_is_left_unasked_is_seen_at_the_next_status_look() -> None:
    async def session() -> None:
        clock = current_clock()
        emulator = Ibm7545Emulator()
        async with running(emulator, CYCLE) as robot:
            started = clock.monotonic()
            clock.call_at(started + 1.0, emulator.set_fault, "servo-error")
            with pytest.raises(RobotHalted, match="servo error"):
                await robot.wait_cycle_end(6, timeout=60, poll=0.002, watch_every=0.25, quiet=30)
            # Told by a status look a watch period after the fault, not at the first DI/DO
            # read 30 s on.
            assert clock.monotonic() - started < 1.0 + 0.25 + 0.2
            assert robot.state == 0

    run_virtual(session())


@pytest.mark.virtual
async def test_a_servo_error_mid_transfer_is_alarmed_within_a_poll_period(tmp_path: Path) -> None:
    """The cell's first transfer (conveyor to CNC 1, some 5 s of the arm's model) leaves its
    end unasked for most of the cycle: a servo error 1 s into it is still one alarm, in the
    status's words, within a poll period, and the part is held."""
    async with CellRig(tmp_path / "cell", time_scale=1.0, deadlines="emulated") as rig:
        clock = current_clock()
        rig.post("wax-robot-base", 1, "A")
        switched: list[float] = []

        def as_the_door_opens(name: str, on: bool) -> None:
            if name == "door_1" and on and not switched:
                switched.append(clock.now() + 1.0)
                clock.call_at(clock.monotonic() + 1.0, rig.switch_on, "robot:servo-error")

        rig.cell.plc.hooks.coil.append(as_the_door_opens)
        controller = await rig.start_controller()
        (alarm,) = await rig.wait_for(lambda: rig.alarms("robot"), "an alarm on the robot")
        assert alarm.text == "servo error"
        assert alarm.raised - switched[0] <= controller.options.poll_period
        (held,) = await rig.wait_for(rig.held_parts, "the part held")
        assert "transfer conveyor_to_cnc1" in (held.note or "")
        assert [r.outcome for r in rig.cell.robot.runs][-1] != "completed"
        await rig.stop_controller()


@pytest.mark.virtual
async def test_a_mill_s_door_is_read_only_near_the_end_of_its_close(tmp_path: Path) -> None:
    """A machining step waits for its mill's door to close (2 s on the PLC's model, 1 s at a
    time scale of 2): the first close is read every 5 ms all the way, later ones only once
    most of the shortest close seen (from its command) has passed. Counted in the PLC's
    requests while door 1 travels shut; the parts are made all the same."""
    slow = {"ready_wait": 30.0, "setup_timeout": 60.0, "block_extra": 30.0}
    async with CellRig(
        tmp_path / "cell",
        time_scale=2.0,
        deadlines="emulated",
        mill_options=slow,
        cell_options={"poll_period": 5.0},  # few looks: the door's own reads are counted
    ) as rig:
        plc = rig.cell.plc
        windows: list[int] = []  # requests served while door 1 closed, one per close
        commanded: list[int] = []

        def door_commanded(name: str, on: bool) -> None:
            if name == "door_1" and not on:
                commanded.append(plc.requests_served)

        def door_arrived(name: str, on: bool) -> None:
            if name == "door_closed_1" and on and commanded:
                windows.append(plc.requests_served - commanded.pop())

        plc.hooks.coil.append(door_commanded)
        plc.hooks.input.append(door_arrived)
        rig.post("wax-robot-base", 2, "A")
        await rig.start_controller()
        await rig.wait_for(lambda: rig.order_state("A") == "done", "order A done", timeout=3600)
        await rig.stop_controller()
        assert not rig.alarms() and not rig.held_parts()
        assert len(windows) >= 3  # each part's transfer in, and out
        assert windows[0] > 100  # polled from the close's start
        assert max(windows[1:]) * 3 < windows[0]
