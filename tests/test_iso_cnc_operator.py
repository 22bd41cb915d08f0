"""The emulated iso-cnc control's automatic operator, as the emulated cell has it: a DC1 the
host never got (lost, or sent while the host was still busy with the last tape) is pressed
again while the control waits for its program, even when stray characters (the last tape's
trailer) came in meanwhile, within the deadline the emulated cell gives its host. Through a
real pty, a raw host on the other end."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest

from cellctl.emulators.serve import CELL_TIME_SCALE, Server, serve
from cellctl.kinds import registry
from cellctl.kinds.iso_cnc import tape
from cellctl.kinds.iso_cnc.emulator import Activity, EmulatorOptions, IsoCncEmulator, Mode
from cellctl.kinds.iso_cnc.tape import DC1, DC3
from cellctl.link import LineSettings, Link, open_link

from .conftest import until

LINE = LineSettings(96000, 7, "E", 2)
PROGRAM = "O0042 (BRACKET)\nG21 G90\nG0 X1 Y2\nM30\n"


def host_deadline() -> float:
    """How long the emulated cell's host waits for a DC1 (its ``dc1_timeout``)."""
    options = registry.kind("iso-cnc").emulated_options
    assert options is not None
    return float(options(CELL_TIME_SCALE)["dc1_timeout"])


@pytest.fixture
async def served() -> AsyncIterator[tuple[IsoCncEmulator, Link]]:
    """A control in EDIT with its automatic operator, and a host on its line."""
    control = IsoCncEmulator(EmulatorOptions(auto_operator=True), time_scale=CELL_TIME_SCALE)
    control.mode = Mode.EDIT
    server: Server = await serve(control, "pty", LINE)
    control.start()
    link = await open_link(server.url, LINE)
    try:
        yield control, link
    finally:
        await link.close()
        await server.close()


async def test_a_lost_dc1_is_asked_again_despite_stray_characters(
    served: tuple[IsoCncEmulator, Link],
) -> None:
    control, link = served
    # READ, pressed as the host connected: its DC1 is the one the host misses.
    assert await link.read_exactly(1, timeout=10) == DC1
    await until(lambda: control.activity == Activity.READING, "the control reading")
    # The last tape's trailer comes in after it: only tape feed, no program.
    await link.write(b"\x00" * 20)
    await until(lambda: control.chars_read == 20, "the trailer through the line")
    # The operator sees the control still waiting and presses READ again, before the
    # cell's host would give up.
    assert await link.read_exactly(1, timeout=host_deadline()) == DC1
    await link.write(tape.frame(PROGRAM, leader=5, trailer=5))
    assert await link.read_until(DC3, timeout=10) == DC3  # the closing %: out of the read
    await until(lambda: 42 in control.memory, "the program in memory")
    assert control.memory[42] == PROGRAM and control.alarms == []
