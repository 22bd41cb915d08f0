"""Dyna2400Mill against the mill emulator, over RFC 2217 (CTS on the line) and a pty (in-band
DC1/DC3 readiness): every function and every result code."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from cellctl.drivers.state import StateStore
from cellctl.emulators.serve import Server, serve
from cellctl.errors import DeviceError, LinkClosed, UsageError
from cellctl.kinds.dyna2400.driver import (
    EXECUTING,
    REFERENCE_ZERO_NOT_SET,
    CallbackOutput,
    Dyna2400Mill,
    MillConfig,
    MillInputError,
    Progress,
)
from cellctl.kinds.dyna2400.dynalan import parse_program
from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator, LinkMode, OperatorDelays
from cellctl.link import LineSettings

PROGRAMS = Path(__file__).resolve().parent.parent / "examples" / "programs"
SETUP = PROGRAMS / "cnc1_setup.dyn"
ROUGH = PROGRAMS / "robot_base_rough_cnc1.dyn"
LONG = PROGRAMS / "toy_mill_table_finish_cnc2.dyn"
FAST_LINE = LineSettings(115200, 8, "N", 1)
READINESS = {"rfc2217": "modem", "pty": "inband"}


@dataclass
class Cell:
    emulator: Dyna2400Emulator
    server: Server
    readiness: str
    store: StateStore

    async def mill(self, **config: object) -> Dyna2400Mill:
        options: dict[str, object] = {"readiness": self.readiness, "pace_writes": False}
        options.update(config)
        return await Dyna2400Mill.connect(
            self.server.url,
            name="cnc1",
            settings=FAST_LINE,
            store=self.store,
            config=MillConfig(**options),  # type: ignore[arg-type]
        )

    async def ready_mill(self, **config: object) -> Dyna2400Mill:
        """A mill initialized and past the operator's NEXT (state 2)."""
        mill = await self.mill(**config)
        await mill.initialize(SETUP)
        await mill._ready.wait(True, 5)
        assert (await mill.status()).state == 2
        return mill


def _emulator(readiness: str, **kw: object) -> Dyna2400Emulator:
    delays = OperatorDelays(power_on=1.0, keys=1.0, setup=100.0)
    return Dyna2400Emulator(
        time_scale=1000.0,
        delays=delays,
        readiness=readiness,
        min_busy_s=0.05,
        **kw,  # type: ignore[arg-type]
    )


@pytest.fixture(params=["rfc2217", "pty"])
async def cell(request: pytest.FixtureRequest, tmp_path: Path) -> AsyncIterator[Cell]:
    readiness = READINESS[request.param]
    emulator = _emulator(readiness)
    listen = "rfc2217://127.0.0.1:0" if request.param == "rfc2217" else f"pty:{tmp_path}/mill"
    server = await serve(emulator, listen, FAST_LINE, pacing=False)
    emulator.start()
    await emulator_ready(emulator)
    yield Cell(emulator, server, readiness, StateStore(tmp_path))
    await server.close()


async def emulator_ready(emulator: Dyna2400Emulator) -> None:
    if emulator._operator is not None:
        await emulator._operator


async def test_initialize_operator_next_then_state_2(cell: Cell) -> None:
    mill = await cell.mill()
    async with mill:
        result = await mill.initialize(SETUP)
        assert result.code == 0 and result.message == "Initializing was correct"
        assert mill.state == 1
        await mill._ready.wait(True, 5)
        status = await mill.status()
        assert status.state == 2 and status.ready and status.condition is None
        assert cell.emulator.reference_zero_set
        assert mill.units is not None and mill.feed["X"] == 10.0


async def test_initialize_refuses_twice_unless_forced(cell: Cell) -> None:
    mill = await cell.ready_mill()
    async with mill:
        with pytest.raises(DeviceError) as info:
            await mill.initialize(SETUP)
        assert info.value.code == 1 and info.value.message == "Machine already initialized"
        assert (await mill.initialize(SETUP, force=True)).code == 0


async def test_initialize_not_ready_is_code_4(cell: Cell) -> None:
    cell.emulator.set_fault("never-ready")
    mill = await cell.mill(ready_wait=0.3)
    async with mill:
        with pytest.raises(DeviceError) as info:
            await mill.initialize(SETUP)
        assert info.value.code == 4 and info.value.message == "Machine not ready"
    assert cell.emulator.memory == {}


@pytest.mark.parametrize(
    "setup", [PROGRAMS / "missing.dyn", PROGRAMS / "broken" / "feed_in_mm_for_ins.dyn"]
)
async def test_initialize_file_error_is_code_5_before_any_byte(cell: Cell, setup: Path) -> None:
    mill = await cell.mill()
    async with mill:
        with pytest.raises(MillInputError) as info:
            await mill.initialize(setup)
        assert info.value.code == 5 and info.value.message == "Initializing file error"
        assert mill.link.bytes_sent <= 1  # at most the in-band readiness enquiry
    assert cell.emulator.memory == {}


async def test_download_before_initialize_is_code_1(cell: Cell) -> None:
    mill = await cell.mill()
    async with mill:
        with pytest.raises(DeviceError) as info:
            await mill.download(ROUGH)
        assert info.value.code == 1 and info.value.message == "Machine not initialized"


async def test_download_before_reference_zero_is_code_2(cell: Cell) -> None:
    cell.emulator.set_fault("no-next")
    mill = await cell.mill()
    async with mill:
        await mill.initialize(SETUP)
        status = await mill.status()
        assert status.state == 1 and status.condition == REFERENCE_ZERO_NOT_SET
        memory = dict(cell.emulator.memory)
        with pytest.raises(DeviceError) as info:
            await mill.download(ROUGH)
        assert info.value.code == 2 and info.value.message == "Absolute zero not set"
    assert cell.emulator.memory == memory


@pytest.mark.parametrize(
    ("program", "code"),
    [(PROGRAMS / "nope.dyn", 4), (PROGRAMS / "broken" / "arc_over_180.dyn", 5)],
)
async def test_download_file_errors_before_any_byte(cell: Cell, program: Path, code: int) -> None:
    mill = await cell.ready_mill()
    async with mill:
        sent = mill.link.bytes_sent
        with pytest.raises(MillInputError) as info:
            await mill.download(program)
        assert info.value.code == code
        assert mill.link.bytes_sent == sent
        if code == 5:
            assert info.value.problems and "arc" in str(info.value)


async def test_download_streams_a_long_program_block_by_block(cell: Cell) -> None:
    mill = await cell.ready_mill()
    cell.emulator.time_scale = 20000.0
    seen: list[Progress] = []
    async with mill:
        result = await mill.download(LONG, progress=seen.append)
        assert result.message == "Download was correct"
        assert mill.state == 2
    runs = [r for r in cell.emulator.runs if r.lines_executed > 100]
    assert len(runs) == 3 and all(r.outcome == "block end" for r in runs)
    assert {p.block for p in seen if p.phase == "sending"} == {1, 2, 3}
    assert seen[-1].phase == "done" and seen[-1].bytes_sent == seen[-1].bytes_total
    assert [t.block for t in mill.last_download] == [1, 2, 3]
    assert cell.emulator.overruns == 0


async def test_download_while_executing_is_code_2_and_status_says_executing(cell: Cell) -> None:
    mill = await cell.ready_mill()
    cell.emulator.time_scale = 20.0  # a block that runs long enough to be seen running
    async with mill:
        await mill.download(ROUGH, wait=False)
        assert mill.state == 3
        status = await mill.status()
        assert status.condition == EXECUTING and not status.ready
        with pytest.raises(DeviceError) as info:
            await mill.download(ROUGH)
        assert info.value.code == 2 and info.value.message == "Machine executing program"
        with pytest.raises(DeviceError):
            await mill.initialize(SETUP)


async def test_download_cut_mid_block_leaves_nothing_running_and_redownload_works(
    cell: Cell,
) -> None:
    mill = await cell.ready_mill()
    runs_before = len(cell.emulator.runs)
    cell.emulator.set_fault("drop", "10")
    with pytest.raises(LinkClosed):
        async with mill:
            await mill.download(ROUGH)
            await mill.status()
    assert not cell.emulator.executing
    assert len(cell.emulator.runs) == runs_before
    assert mill.state == 2
    again = await cell.mill()
    async with again:
        assert again.state == 2  # the saved view survived the reconnect
        assert (await again.download(ROUGH)).code == 0
    assert cell.emulator.runs[-1].outcome == "block end"
    assert cell.emulator.runs[-1].lines_executed > 40


async def test_stalled_controller_gives_machine_executing_with_a_deadline(cell: Cell) -> None:
    mill = await cell.ready_mill(block_extra=0.5, block_margin=0.0)
    cell.emulator.set_fault("stall")
    async with mill:
        with pytest.raises(DeviceError) as info:
            await mill.download(LONG)
        assert info.value.code == 2 and "block 1 of 3" in str(info.value)


async def test_end_returns_the_controller_to_manual_state_0(cell: Cell) -> None:
    mill = await cell.ready_mill()
    async with mill:
        result = await mill.end()
        assert result.message == "Ending was correct"
        assert mill.state == 0 and not mill.initialized
        assert (await mill.status()).state == 0
        assert cell.emulator.runs[-1].outcome == "END"
        # The operator readies the controller again: the host initializes it anew.
        await mill._ready.wait(True, 5)
        assert (await mill.initialize(SETUP)).message == "Initializing was correct"
        assert mill.state == 1


async def test_state_is_kept_per_machine_across_connections(cell: Cell) -> None:
    mill = await cell.ready_mill()
    await mill.close()
    again = await cell.mill()
    async with again:
        assert again.state == 2 and again.initialized and again.feed["Z"] == 10.0
    assert StateStore(cell.store.dir.parent).load("cnc1")["state"] == 2


async def test_load_then_go_through_the_start_output(cell: Cell) -> None:
    cell.emulator.select(LinkMode.PROGRAM_LOAD)
    mill = await cell.mill()
    mill.start_output = CallbackOutput(cell.emulator.cycle_start)
    async with mill:
        assert (await mill.load(ROUGH)).code == 0
        assert mill.loaded == ROUGH.name
        async with asyncio.timeout(5):
            await cell.emulator.transmission_ended.wait()
        assert cell.emulator.display == "LOADED 46"
        assert (await mill.go()).code == 0
        assert mill.state == 4
        await mill._ready.wait(True, 10)
    assert cell.emulator.runs[-1].outcome == "block end"


async def test_load_refuses_more_than_900_lines_and_go_needs_an_output(cell: Cell) -> None:
    mill = await cell.mill()
    async with mill:
        with pytest.raises(MillInputError, match="at most 900 lines"):
            await mill.load(LONG)
        with pytest.raises(UsageError, match="start output"):
            await mill.go()


async def test_upload_returns_the_controllers_memory(cell: Cell) -> None:
    mill = await cell.ready_mill()
    async with mill:
        await mill.download(ROUGH)
        cell.emulator.select(LinkMode.UPLOAD)
        text = await mill.upload(timeout=5)
    rows = text.splitlines()
    assert rows[0].startswith("000 ; WAX SCARA ROBOT BASE")
    assert rows[-1] == "900"


async def test_line_execute_runs_one_line_at_a_time(cell: Cell) -> None:
    cell.emulator.select(LinkMode.LINE_EXECUTE)
    mill = await cell.mill()
    async with mill:
        text = "000 FR XY = 20.0\n001 GO X 1.000\n002   Y 2.000\n003 GR X .500\n"
        assert (await mill.line_execute(parse_program(text, name="L"))).code == 0
    position = cell.emulator.machine.position
    assert position[0] == pytest.approx(1.5) and position[1] == pytest.approx(2.0)


async def test_connect_refuses_a_link_without_modem_lines_unless_inband(
    tmp_path: Path,
) -> None:
    emulator = _emulator("modem")
    server = await serve(emulator, "pty", FAST_LINE, pacing=False)
    try:
        with pytest.raises(UsageError, match="inband"):
            await Dyna2400Mill.connect(server.url, settings=FAST_LINE)
    finally:
        await server.close()


async def test_a_program_edited_between_two_downloads_is_checked_again(
    cell: Cell, tmp_path: Path
) -> None:
    """What a file validated to is kept for the next run of the same text, never for an edited
    one: the edit is refused (code 5) before a byte goes out."""
    program = tmp_path / "part.dyn"
    program.write_text(ROUGH.read_text())
    mill = await cell.ready_mill()
    async with mill:
        first = mill.check(program)
        assert first.ok and mill.check(program) is first  # the same text: kept
        await mill.download(program)
        program.write_text((PROGRAMS / "broken" / "arc_over_180.dyn").read_text())
        sent = mill.link.bytes_sent
        with pytest.raises(MillInputError) as info:
            await mill.download(program)
        assert info.value.code == 5 and "arc" in str(info.value)
        assert mill.link.bytes_sent == sent
        assert not mill.check(program).ok
