"""Each kind's driver and emulator over mem:// on virtual time, against the same session
over a real pty (robot) or TCP and RFC 2217 (the mill: DC1/DC3, then CTS on the line): byte
for byte the same traffic, and the
virtual run takes the line's time (plus the machine's own, for the mill) in virtual seconds.

The real runs use fast settings (time scale, no pacing); the virtual runs use the machines'
own lines and times, which is what a plan needs. Wall times are printed, never asserted.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from cellctl.clock import current_clock, run_virtual
from cellctl.drivers.state import StateStore
from cellctl.emulators.cell import EmulatedCell
from cellctl.emulators.memserve import serve_mem
from cellctl.emulators.serve import EmulatedDevice, Server, serve
from cellctl.errors import MachineInUse
from cellctl.kinds.dyna2400.driver import Dyna2400Mill, MillConfig
from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator, OperatorDelays
from cellctl.kinds.ibm7545.aml import compile_source
from cellctl.kinds.ibm7545.driver import Ibm7545Robot
from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator
from cellctl.link import MILL_LINE, ROBOT_LINE, LineSettings, TrafficLog
from cellctl.link.mem import PACE_SLICE_S
from cellctl.link.trace import RECEIVED

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
ROBOT_PROGRAMS = sorted((EXAMPLES / "robot").glob("*.aml"))
SETUP = EXAMPLES / "programs" / "cnc1_setup.dyn"
LONG = EXAMPLES / "programs" / "toy_mill_table_finish_cnc2.dyn"
FAST_LINE = LineSettings(115200, 8, "N", 1)


@dataclass
class Run:
    """One session: its traffic, and the download's clock time and bytes (both ways)."""

    trace: TrafficLog
    elapsed: float = 0.0
    download_bytes: int = 0
    wall: float = 0.0
    machine_s: float = 0.0  # machine time the download's blocks took (the mill)
    device_in: int = 0  # bytes the emulator's end received, and sent
    device_out: int = 0
    held: object = None  # what the machine holds after the session (partitions, memory)

    def turns(self) -> list[tuple[str, bytes]]:
        """The traffic as turns: each run of bytes one way, however it was chunked."""
        turns: list[tuple[str, bytes]] = []
        for _, _, direction, data in self.trace.entries:
            if turns and turns[-1][0] == direction:
                turns[-1] = (direction, turns[-1][1] + data)
            else:
                turns.append((direction, data))
        return turns

    def total(self) -> int:
        return len(self.trace.sent()) + len(self.trace.received())

    def device_side(self, server: Server, held: object) -> None:
        """What reached the emulator: the host's trace is taken before the line."""
        line = server.current_line
        assert line is not None
        self.device_in, self.device_out, self.held = line.bytes_in, line.bytes_out, held

    def check_line(self) -> None:
        """Every byte crossed the line: as many reached each end as the other sent."""
        assert (self.device_in, self.device_out) == (
            len(self.trace.sent()),
            len(self.trace.received()),
        )


def timed(run: Run, session: Callable[[], Awaitable[None]], virtual: bool) -> Run:
    wall = time.perf_counter()
    if virtual:
        run_virtual(session())  # type: ignore[arg-type]
    else:
        asyncio.run(session())  # type: ignore[arg-type]
    run.wall = time.perf_counter() - wall
    return run


async def serve_on(device: EmulatedDevice, listen: str, line: LineSettings) -> Server:
    if listen == "mem":
        return await serve_mem(device, line, name="machine1")
    return await serve(device, listen, line, pacing=False)


# -- the robot ---------------------------------------------------------------------------------


def robot_run(listen: str, line: LineSettings, time_scale: float, state: Path) -> Run:
    run = Run(TrafficLog(None))
    programs = [compile_source(p.read_text(), p.stem.upper()[:8], 1) for p in ROBOT_PROGRAMS]

    async def session() -> None:
        emulator = Ibm7545Emulator(time_scale=time_scale)
        server = await serve_on(emulator, listen, line)
        clock = current_clock()
        try:
            robot = await Ibm7545Robot.connect(
                server.url, name="robot1", settings=line, store=StateStore(state), trace=run.trace
            )
            async with robot:
                await robot.initialize()
                before, start = run.total(), clock.monotonic()
                for partition, program in enumerate(programs, start=1):
                    await robot.download(partition, program)
                run.elapsed = clock.monotonic() - start
                run.download_bytes = run.total() - before
                assert all(robot.partitions[p] for p in range(1, len(programs) + 1))
                run.device_side(server, dict(emulator.partitions))
        finally:
            await server.close()

    return timed(run, session, virtual=listen == "mem")


def test_robot_downloads_over_mem_on_virtual_time_as_over_a_pty(tmp_path: Path) -> None:
    real = robot_run("pty", ROBOT_LINE, 200.0, tmp_path / "pty")
    mem = robot_run("mem", ROBOT_LINE, 1.0, tmp_path / "mem")
    assert mem.turns() == real.turns()
    assert any(direction == RECEIVED for direction, _ in mem.turns())
    mem.check_line()
    assert mem.held == real.held  # the same programs arrived in the same partitions
    # The downloads are record and Ack in turn: their time is the line's, both ways.
    line_time = ROBOT_LINE.wire_time(mem.download_bytes)
    assert mem.elapsed == pytest.approx(line_time, abs=PACE_SLICE_S)
    print(
        f"\nrobot: {len(ROBOT_PROGRAMS)} downloads, {mem.download_bytes} bytes; mem:// "
        f"{mem.elapsed:.3f} s virtual (line time {line_time:.3f} s) in {mem.wall:.3f} s wall "
        f"({mem.elapsed / mem.wall:.0f}x); pty session {real.wall:.3f} s wall (not paced)"
    )


def test_a_second_driver_on_a_served_mem_line_is_refused(tmp_path: Path) -> None:
    async def session() -> None:
        server = await serve_mem(Ibm7545Emulator(), ROBOT_LINE)
        robot = await Ibm7545Robot.connect(server.url, name="robot1")
        try:
            with pytest.raises(MachineInUse, match="in use"):
                await Ibm7545Robot.connect(server.url, name="robot1b")
            await robot.initialize()
            assert robot.state == 1
        finally:
            await robot.close()
            await server.close()

    run_virtual(session())


# -- the mill ----------------------------------------------------------------------------------


@contextlib.asynccontextmanager
async def ready_mill(
    emulator: Dyna2400Emulator,
    url: str,
    line: LineSettings,
    state: Path,
    config: MillConfig,
    trace: TrafficLog | None = None,
) -> AsyncIterator[Dyna2400Mill]:
    """The emulated mill at ``url`` powered on (its operator done), then a driver on it,
    initialized with :data:`SETUP` and ready (CTS high); closed after."""
    emulator.start()
    assert emulator._operator is not None
    await emulator._operator
    mill = await Dyna2400Mill.connect(
        url, name="cnc1", settings=line, store=StateStore(state), config=config, trace=trace
    )
    async with mill:
        await mill.initialize(SETUP)
        await mill._ready.wait(True, 300)
        yield mill


def mill_run(listen: str, readiness: str, virtual: bool, state: Path) -> Run:
    run = Run(TrafficLog(None))
    if virtual:  # the machine's own line and times
        line, emulator = MILL_LINE, Dyna2400Emulator(readiness=readiness)
    else:
        line = FAST_LINE
        emulator = Dyna2400Emulator(
            time_scale=20000.0,
            delays=OperatorDelays(power_on=1.0, keys=1.0, setup=100.0),
            readiness=readiness,
            min_busy_s=0.05,
        )

    async def session() -> None:
        server = await serve_on(emulator, listen, line)
        clock = current_clock()
        # The real run writes as fast as it can (the same bytes, sooner); the virtual one
        # paces its writes as a controller does.
        config = MillConfig(readiness=readiness, pace_writes=virtual)  # type: ignore[arg-type]
        try:
            async with ready_mill(emulator, server.url, line, state, config, run.trace) as mill:
                before, start, runs = run.total(), clock.monotonic(), len(emulator.runs)
                await mill.download(LONG)
                run.elapsed = clock.monotonic() - start
                run.download_bytes = run.total() - before
                blocks = emulator.runs[runs:]
                assert [b.outcome for b in blocks] == ["block end"] * 3
                run.machine_s = sum(
                    max(b.machining_s / emulator.time_scale, emulator.min_busy_s) for b in blocks
                )
                run.device_side(server, dict(emulator.memory))
        finally:
            await server.close()

    return timed(run, session, virtual=virtual)


@pytest.mark.parametrize(
    ("real_listen", "readiness"),
    # In-band readiness is what a line without modem lines needs: raw TCP here, not a pty,
    # because a pty's session begins before the host opens it (whose open then flushes the
    # greeting DC1), where TCP and mem:// begin a session per connection.
    [("socket://127.0.0.1:0", "inband"), ("rfc2217://127.0.0.1:0", "modem")],
    ids=["socket-inband", "rfc2217-cts"],
)
def test_mill_downloads_over_mem_on_virtual_time_as_over_a_real_line(
    tmp_path: Path, real_listen: str, readiness: str
) -> None:
    real = mill_run(real_listen, readiness, False, tmp_path / "real")
    mem = mill_run("mem", readiness, True, tmp_path / "mem")
    assert mem.trace.sent() == real.trace.sent()
    assert mem.trace.received() == real.trace.received()
    assert mem.turns() == real.turns()
    mem.check_line()
    assert mem.held == real.held  # the controller's memory: the last block, line for line
    # Three blocks, each sent at the line's rate, then machined on the machine's own time.
    line_time = MILL_LINE.wire_time(mem.download_bytes)
    assert mem.elapsed == pytest.approx(line_time + mem.machine_s, abs=PACE_SLICE_S)
    print(
        f"\nmill ({readiness}): 3 blocks, {mem.download_bytes} bytes; mem:// {mem.elapsed:.1f} s "
        f"virtual (line {line_time:.1f} s + machining {mem.machine_s:.1f} s) in "
        f"{mem.wall:.3f} s wall ({mem.elapsed / mem.wall:.0f}x); {real_listen} session "
        f"{real.wall:.3f} s wall at time scale 20000"
    )


def test_an_emulated_cell_started_with_a_part_in_a_vise_has_it_clamped(tmp_path: Path) -> None:
    async def started() -> tuple[bool, bool, bool, dict[int, str | None]]:
        cell = EmulatedCell(time_scale=1.0, links="mem")
        await cell.start(tmp_path / "cell")
        try:
            cell.place("cnc2", "X")
            await current_clock().sleep(cell.plc.timing.clamp_s + 0.1)  # the vise's travel
            return (cell.robot.output(2), cell.plc.coils["clamp_2"],
                    cell.plc.inputs["clamp_closed_2"], dict(cell.vise))  # fmt: skip
        finally:
            await cell.close()

    output, coil, closed, vises = run_virtual(started())
    # As the robot's place leaves it: its vise output on, the coil and the sensor following.
    assert (output, coil, closed) == (True, True, True)
    assert vises == {1: None, 2: "X"}
