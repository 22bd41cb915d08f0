"""A drip-feed whose line drops part-way (the device server, or the emulator, gone): the
command's progress bar ends its line before the error, and the error and the machine's log
say where the tape ended (characters, and the last block sent whole, which an integrator
restarts from), as `dnc stop` does. A real `cellctl dnc drip` against an emulated control
over TCP; the tape's own arithmetic on its own below."""

from __future__ import annotations

import re
from pathlib import Path

from cellctl.kinds.iso_cnc import tape
from cellctl.kinds.iso_cnc.dnc.store import ShopStore
from cellctl.kinds.iso_cnc.transfer import TapeEnd
from tests.conftest import until
from tests.test_dnc_cli import Shop, finished, shop  # noqa: F401  (shop: a fixture)
from tests.test_dnc_hand import hand_drip
from tests.test_dnc_server import surfacing
from tests.test_dnc_stop import MOVES

ENDED = re.compile(
    r"; the tape ended at (\d+) of (\d+) characters, after block (\d+) \(([^)]*)\): the "
    r"control ran at most that far"
)


async def test_a_dropped_line_ends_the_bar_then_says_where_the_tape_ended(
    shop: Shop,  # noqa: F811
    tmp_path: Path,
) -> None:
    text = surfacing(MOVES)
    program = tmp_path / "surface.nc"
    program.write_text(text)
    control = shop.controls["mill2"]
    async with hand_drip(shop, program) as drip:
        await until(lambda: control.chars_read > 2000, "the drip-feed under way", 30)
        await shop.servers[1].close()  # the device server goes: the line drops
        code, told = await finished(drip, 60)
    assert code == 3, told  # the link's failure
    lines = told.splitlines()
    bars = [i for i, line in enumerate(lines) if line.startswith("surface.nc") and "chars" in line]
    errors = [i for i, line in enumerate(lines) if "error:" in line]
    # One bar line, ended (failed, no time left) before the error, which has a line of its own.
    assert len(bars) == 1 and len(errors) == 1, told
    assert bars[0] < errors[0] and lines[errors[0]].startswith("error: "), told
    assert lines[bars[0]].rstrip().endswith("failed") and "error" not in lines[bars[0]], told
    said = " ".join(" ".join(lines[errors[0] :]).split())
    found = ENDED.search(said)
    assert found, said
    sent, total, block, shown = int(found[1]), int(found[2]), int(found[3]), found[4]
    framed_total = len(tape.frame(text))  # the tape as the driver frames it (no leader)
    assert total >= framed_total and 2000 < sent < total, said
    # The block it names is the program's own, counted from its O block as block 1.
    assert text.splitlines()[block - 1] == shown, (block, shown)
    assert "modal state" in said and "G-codes" in said, said
    log = "\n".join(ShopStore(shop.root).log_lines("mill2"))
    assert "surface.nc: drip-fed FAILED: " in log and f"ended at {sent} of {total}" in log, log
    # A one-shot command's machine: nothing tries its link again, and nothing says so.
    assert "tried again" not in told + log, told + log


def test_where_a_tape_ended_counts_the_programs_blocks() -> None:
    program = "O1234 (PART)\nG21 G90\nG01 X1. F300\nM30\n"
    framed = tape.frame(program, leader=10, trailer=10)
    body = framed.index(b"O1234")
    # In the leader, or the opening % and its label: no block of the program yet.
    assert TapeEnd.of(framed, 5).block == 0
    assert TapeEnd.of(framed, body).block == 0
    # Mid-block: the blocks before it were whole; the one in flight is not counted.
    mid = framed.index(b"X1.")
    end = TapeEnd.of(framed, mid)
    assert (end.sent, end.total, end.block, end.text) == (mid, len(framed), 2, "G21 G90")
    assert not end.all_out
    assert "after block 2 (G21 G90)" in end.words(drip=True)
    assert "read it in again" in end.words(drip=False)
    # Every block and the closing % out, only the trailer missing: all of it was out.
    closing = framed.rindex(b"%") + 1
    assert TapeEnd.of(framed, closing).all_out
    assert TapeEnd.of(framed, closing).words(drip=False).startswith("all ")
    assert not TapeEnd.of(framed, closing - 1).all_out
