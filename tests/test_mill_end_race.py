"""END after a download cut short (an emergency stop, the controller's abort): the mill must
end up in manual mode whatever moment the cut came at.

The moment that matters is a block sent whole but not yet taken: its last lines are still on
the wire (the driver writes up to a quarter of a second ahead), CTS is still high, and the
controller starts the block the moment its ``900`` line arrives. An END sent then arrives
while the block runs and is lost, and the CTS fall of the block looks like the END's return
to manual. The driver waits such a block out before END.

The Dyna 2400 emulator and its driver over ``mem://`` on virtual time: the machine's own line
and times, and the same bytes as over a pty.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

from cellctl.clock import current_clock
from cellctl.emulators.memserve import serve_mem
from cellctl.kinds.dyna2400.driver import Dyna2400Mill, MillConfig
from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator, LinkMode
from cellctl.link import MILL_LINE
from tests.test_mem_emulators import ready_mill

#: Two blocks as the controller takes them (each closed by SKIP TO 900 / 900): the first is
#: long enough (about 0.7 s of line) that half of it is not yet written when half is sent.
TWO_BLOCKS = (
    "000 FR XY = 5.0\n"
    + "".join(f"{n:03d} GO X {n % 2}.000\n{n + 1:03d} GO Y {n % 2}.000\n" for n in range(1, 21, 2))
    + "021 SKIP TO 900\n900\n"
    + "000 GO X 0.500\n001 GO Y 0.500\n002 GO X 0.000\n003 SKIP TO 900\n900\n"
)


def _cut_at(mill: Dyna2400Mill, program: Path, moment: str) -> Any:
    """The progress callback that says when to cut the download short: at ``moment``."""
    blocks = mill.check(program).blocks
    assert blocks is not None and len(blocks) == 2
    first = len(blocks[0].lines)
    cut = asyncio.Event()

    def progress(p: Any) -> None:
        if p.phase == "sending" and p.block == 1 and moment == "mid-block":
            hit = p.lines_sent >= first // 2
        elif p.phase == "sending" and moment == "block sent, not taken":
            hit = p.lines_sent == first  # its last line written, CTS not fallen yet
        else:
            hit = p.phase == "machining" and moment == "block running"
        if hit:
            cut.set()

    return progress, cut


@pytest.mark.virtual
@pytest.mark.parametrize(
    ("moment", "runs"),
    [
        ("mid-block", ["END"]),  # never complete: it never starts, END takes its line 000
        ("block sent, not taken", ["block end", "END"]),  # it runs, then END
        ("block running", ["block end", "END"]),
    ],
)
async def test_end_after_a_cut_short_download_leaves_the_mill_in_manual(
    tmp_path: Path, moment: str, runs: list[str]
) -> None:
    emulator = Dyna2400Emulator()
    server = await serve_mem(emulator, MILL_LINE, name="cnc1")
    clock = current_clock()
    state, config = tmp_path / "state.json", MillConfig(pace_writes=True)
    try:
        async with ready_mill(emulator, server.url, MILL_LINE, state, config) as mill:
            program = tmp_path / "two.dyn"
            program.write_text(TWO_BLOCKS)
            progress, cut = _cut_at(mill, program, moment)
            before = len(emulator.runs)
            download = asyncio.create_task(mill.download(program, progress=progress))
            async with clock.timeout(600):
                await cut.wait()
            download.cancel()
            with pytest.raises(asyncio.CancelledError):
                await download
            # What the cell's emergency stop does: no more blocks, END once it is ready.
            async with clock.timeout(600):
                while mill.running and not (await mill.status()).ready:
                    await clock.sleep(0.05)
                result = await mill.end()
            assert result.code == 0
            assert emulator.mode is LinkMode.MANUAL, (emulator.display, emulator.runs[before:])
            assert not emulator.executing
            assert mill.state == 0 and not mill.initialized
            # Nothing runs after the END (the automatic operator readies it again later).
            await clock.sleep(120)
            assert [r.outcome for r in emulator.runs[before:]] == runs
    finally:
        await server.close()
