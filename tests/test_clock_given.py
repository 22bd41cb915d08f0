"""The one clock handed in: emulators' time scales are their clocks', and what is made without
a clock reads the running loop's (docs/clock.md, "Who is given a clock")."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest

from cellctl.cell.journal import open_journal
from cellctl.clock import REAL_CLOCK, RealClock, VirtualClock, current_clock, run_virtual
from cellctl.emulators.cell import EmulatedCell
from cellctl.emulators.memserve import serve_mem
from cellctl.emulators.plc import PlcEmulator
from cellctl.errors import UsageError
from cellctl.kinds import registry
from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator
from cellctl.kinds.ibm7545.driver import Ibm7545Robot
from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator
from cellctl.kinds.kind import EmulatorSpec
from cellctl.kinds.ur.emulator import UrEmulator
from cellctl.link import ROBOT_LINE
from cellctl.mailbox.sqlite import SqliteMailbox

SHIFT_START = datetime(2026, 11, 27, 6, 0, tzinfo=UTC)


class CountingClock:
    """The running loop's clock, counting how often it is read: a clock handed to a driver."""

    def __init__(self) -> None:
        self.reads = 0

    @property
    def time_scale(self) -> float:
        return 1.0

    def now(self) -> float:
        self.reads += 1
        return current_clock().now()

    def monotonic(self) -> float:
        self.reads += 1
        return current_clock().monotonic()

    async def sleep(self, seconds: float) -> None:
        await current_clock().sleep(seconds)

    def timeout(self, seconds: float | None) -> asyncio.Timeout:
        return current_clock().timeout(seconds)

    def call_at(self, when: float, callback: Callable[..., object], *args: Any) -> Any:
        return current_clock().call_at(when, callback, *args)


@pytest.mark.parametrize(
    "make",
    [
        lambda **kw: Dyna2400Emulator(**kw),
        lambda **kw: Ibm7545Emulator(**kw),
        lambda **kw: PlcEmulator(**kw),
        lambda **kw: UrEmulator(**kw),
    ],
    ids=["dyna2400", "ibm7545", "plc", "ur"],
)
def test_an_emulators_time_scale_is_its_clocks(make: Callable[..., Any]) -> None:
    shorthand = make(time_scale=100.0)
    assert isinstance(shorthand.clock, RealClock) and shorthand.clock.time_scale == 100.0
    assert shorthand.time_scale == 100.0
    given = RealClock(20.0)
    assert make(clock=given).clock is given and make(clock=given).time_scale == 20.0
    assert make(clock=given, time_scale=20.0).clock is given
    with pytest.raises(UsageError, match="a clock or a time scale, not both"):
        make(clock=given, time_scale=5.0)
    with pytest.raises(UsageError, match="time scale must be a positive number"):
        make(time_scale=0.0)
    # No clock, or a scale of 1: the running loop's clock, whichever it is when used.
    assert make().clock is REAL_CLOCK and make(time_scale=1.0).clock is REAL_CLOCK
    changed = make()
    changed.time_scale = 7.0  # what a test does to make one machine faster
    assert isinstance(changed.clock, RealClock) and changed.clock.time_scale == 7.0


def test_an_emulator_spec_hands_its_clock_to_every_kinds_emulator() -> None:
    given = RealClock(40.0)
    spec = EmulatorSpec(clock=given)
    assert spec.time_scale == 40.0
    for name in ("dyna2400", "ibm7545", "iso-cnc", "ur"):
        emulator = registry.kind(name).emulator(spec)
        assert emulator.clock is given, name
        assert emulator.time_scale == 40.0, name
    scaled = registry.kind("dyna2400").emulator(EmulatorSpec(time_scale=50.0))
    assert isinstance(scaled.clock, RealClock) and scaled.time_scale == 50.0
    with pytest.raises(UsageError, match="not both"):
        EmulatorSpec(time_scale=3.0, clock=given)
    # The emulated cell's machines and PLC all run on the cell's clock.
    cell = EmulatedCell(clock=given)
    assert cell.time_scale == 40.0 and cell.plc.clock is given
    assert cell.robot.clock is given and all(m.clock is given for m in cell.mills.values())
    assert EmulatedCell().time_scale == 50.0  # its default scale, on the real clock


def test_what_is_made_before_the_loop_reads_the_loops_clock_once_it_runs(tmp_path: Path) -> None:
    emulator = Dyna2400Emulator()
    journal = open_journal(tmp_path)
    mailbox = SqliteMailbox(tmp_path / "mailbox.sqlite3")

    async def shift() -> tuple[Any, float, float, float]:
        clock = current_clock()
        order, _ = mailbox.post_order("wax-robot-base", qty=1, order_id="A1")
        await asyncio.sleep(3600)  # an hour of virtual time
        [part] = journal.create_parts(order)
        step = journal.begin_step(part.id, "transfer", "robot", "conveyor_to_cnc1")
        return emulator.clock, clock.now(), order.created, step.started

    with journal, mailbox:
        emulator_clock, now, created, started = run_virtual(shift(), start=SHIFT_START)
    assert isinstance(emulator_clock, VirtualClock)
    assert created == SHIFT_START.timestamp()
    assert started == now == SHIFT_START.timestamp() + 3600


def test_a_driver_given_a_clock_times_its_link_and_waits_on_it(tmp_path: Path) -> None:
    given = CountingClock()

    async def session() -> tuple[bool, bool, int]:
        server = await serve_mem(Ibm7545Emulator(), ROBOT_LINE)
        try:
            robot = await Ibm7545Robot.connect(server.url, name="robot1", clock=given)
            async with robot:
                before = given.reads
                await robot.initialize()
                return robot.clock is given, robot.link.clock is given, given.reads - before
        finally:
            await server.close()

    driver_has_it, link_has_it, reads = run_virtual(session(), start=SHIFT_START)
    assert driver_has_it and link_has_it
    assert reads > 0  # the exchange's deadlines were read from the clock handed in


def test_a_real_clock_on_a_virtual_loop_is_refused_before_a_byte_moves() -> None:
    async def serve_scaled() -> None:
        await serve_mem(Dyna2400Emulator(time_scale=100.0), ROBOT_LINE)

    with pytest.raises(UsageError, match=r"Dyna2400Emulator was given RealClock.*virtual"):
        run_virtual(serve_scaled(), start=SHIFT_START)

    async def open_with_real_clock() -> None:
        server = await serve_mem(Ibm7545Emulator(), ROBOT_LINE)
        try:
            await Ibm7545Robot.connect(server.url, name="robot1", clock=RealClock())
        finally:
            await server.close()

    with pytest.raises(UsageError, match=r"link mem://.* was given RealClock"):
        run_virtual(open_with_real_clock(), start=SHIFT_START)
