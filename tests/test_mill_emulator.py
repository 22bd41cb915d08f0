"""The mill emulator on its own, driven with raw bytes over RFC 2217: what a host that does not
validate sees (stale lines, a malformed line), block start rules, END, Ctrl-Z."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest

from cellctl.emulators.serve import Server, serve
from cellctl.errors import UsageError
from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator, LinkMode, OperatorDelays
from cellctl.link import LineSettings, Link, open_link

FAST_LINE = LineSettings(115200, 8, "N", 1)


@pytest.fixture
async def served() -> AsyncIterator[tuple[Dyna2400Emulator, Server, Link]]:
    emulator = Dyna2400Emulator(
        time_scale=1000.0, delays=OperatorDelays(1.0, 1.0, 10.0), min_busy_s=0.05
    )
    server = await serve(emulator, "rfc2217://127.0.0.1:0", FAST_LINE, pacing=False)
    emulator.start()
    link = await open_link(server.url, FAST_LINE)
    await link.wait_cts(True, timeout=5)
    yield emulator, server, link
    await link.close()
    await server.close()


def lines(*rows: str) -> bytes:
    return b"".join(row.encode() + b"\r\n" for row in rows)


async def run_block(link: Link, data: bytes) -> None:
    """Send a block and wait until the controller took it and is READY again."""
    await link.write(data)
    await link.wait_cts(False, timeout=5)
    await link.wait_cts(True, timeout=5)


async def test_block_runs_only_once_skip_to_900_and_900_arrived(served) -> None:  # type: ignore[no-untyped-def]
    emulator, _, link = served
    await link.write(lines("000 GO X 1.000", "001 SKIP TO 900"))
    await link.write(lines("002 GO Y 1.000"))  # 900 not yet: nothing runs
    await link.write(lines("900") + b"\x1a")
    await link.wait_cts(False, timeout=5)
    await link.wait_cts(True, timeout=5)
    assert emulator.runs[-1].outcome == "block end"
    assert emulator.machine.position[:2] == (1.0, 0.0)  # SKIP TO 900 jumped over line 002


async def test_stale_lines_of_a_longer_block_run_in_a_gap(served) -> None:  # type: ignore[no-untyped-def]
    emulator, _, link = served
    await run_block(
        link, lines("000 GO X 1.000", "001 GO Y 1.000", "002 GO X 2.000", "003 SKIP TO 900", "900")
    )
    # A host that numbers with a gap: the old line 001 is still in memory and runs.
    await run_block(link, lines("000 GO X 3.000", "002 GO X 4.000", "003 SKIP TO 900", "900"))
    assert emulator.memory[1] == "GO Y 1.000"
    assert emulator.runs[-1].lines_executed == 5
    assert emulator.machine.position[:2] == (4.0, 1.0)


async def test_malformed_line_puts_the_controller_in_an_error_condition(served) -> None:  # type: ignore[no-untyped-def]
    emulator, _, link = served
    await link.write(lines("000 GO X 1.000", "001 GO X 1.2.3", "002 SKIP TO 900", "900"))
    await link.wait_cts(False, timeout=5)
    async with asyncio.timeout(5):
        await emulator.failed.wait()
    assert emulator.error is not None
    assert "line 001" in emulator.error and emulator.display.startswith("ERROR")
    assert not await link.cts()
    emulator.clear_memory()
    assert emulator.error is None and emulator.memory == {}


async def test_move_outside_travel_is_an_error_condition(served) -> None:  # type: ignore[no-untyped-def]
    emulator, _, link = served
    at = emulator.machine.position
    await link.write(lines("000 GO X 9.000", "001 SKIP TO 900", "900"))
    await link.wait_cts(False, timeout=5)
    async with asyncio.timeout(5):
        await emulator.failed.wait()
    assert emulator.error is not None
    assert "X travel" in emulator.error
    assert emulator.machine.position == at  # the move was refused, not made
    # The operator at the panel (a plan's after a fault): memory cleared, READY again, the
    # reference zero as it was; the next block runs.
    zero = emulator.reference_zero_set
    await emulator.operator_clear()
    assert emulator.error is None and emulator.display == "READY"
    await link.wait_cts(True, timeout=5)
    assert emulator.reference_zero_set == zero
    await run_block(link, lines("000 GO X 1.000", "001 SKIP TO 900", "900"))
    assert emulator.runs[-1].outcome == "block end"


async def test_the_operator_leaves_a_block_running_alone(served) -> None:  # type: ignore[no-untyped-def]
    """No error: nothing to clear, and a block under way goes on (its READY is its end)."""
    emulator, _, link = served
    # 5 in at 1 in/min: 300 s of machine time, 0.3 s here (still running once CTS is low).
    await link.write(lines("000 FR XYZ = 1.0", "001 GR X 5.000", "002 SKIP TO 900", "900"))
    await link.wait_cts(False, timeout=5)
    await emulator.operator_clear()
    assert emulator.executing and not await link.cts()
    await link.wait_cts(True, timeout=10)
    assert emulator.runs[-1].outcome == "block end"


async def test_end_returns_to_manual_then_the_operator_readies_it_again(served) -> None:  # type: ignore[no-untyped-def]
    emulator, _, link = served
    ready_mode = emulator.mode
    at_end: list[tuple[str, LinkMode, str, bool]] = []
    emulator.run_hooks.append(
        lambda run: at_end.append((run.outcome, emulator.mode, emulator.display, emulator.rts))
    )
    await link.write(lines("000 END") + b"\x1a")
    await link.wait_cts(False, timeout=5)
    assert at_end == [("END", LinkMode.MANUAL, "MANUAL", False)]
    # The automatic operator walks back to the panel: READY again, for the host's INITIALIZE.
    await link.wait_cts(True, timeout=5)
    assert emulator.mode is ready_mode and emulator.display == "READY"


def test_unknown_fault_is_refused() -> None:
    with pytest.raises(UsageError, match="unknown fault"):
        Dyna2400Emulator().set_fault("melt")
