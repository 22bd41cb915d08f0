"""Defects a tester found in ``cellctl dnc``, each on the real path (``cellctl`` in its own
process, emulated controls over a pty and TCP, the DNC server over ``mem://`` on virtual
time): a ``%`` inside a block, the wait for DC1, a request's lapse, stalls in wall seconds,
a drip-feed's totals from its first figure on."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

from cellctl.clock import current_clock, run_virtual
from cellctl.emulators.memserve import serve_mem
from cellctl.kinds.iso_cnc.dnc.config import load_shop
from cellctl.kinds.iso_cnc.dnc.diff import compare
from cellctl.kinds.iso_cnc.dnc.line import REQUEST_WAIT_S
from cellctl.kinds.iso_cnc.dnc.server import Activity, DncServer
from cellctl.kinds.iso_cnc.dnc.store import ShopStore
from cellctl.kinds.iso_cnc.emulator import EmulatorOptions, IsoCncEmulator, Mode
from cellctl.kinds.iso_cnc.gcode import check
from cellctl.link import LineSettings
from tests.conftest import until
from tests.test_dnc_cli import (  # noqa: F401  (shop is a fixture)
    Shop,
    cellctl,
    finished,
    shop,
)
from tests.test_dnc_server import write_shop

STEPOVER = "%\nO1270 (10% STEPOVER)\nG21 G90\nG0 X0 Y0\nM30\n%\n"
LINE = LineSettings.parse("9600,7E2")


def test_a_percent_inside_a_comment_is_one_problem_at_its_line_and_column() -> None:
    found = [f.format("O1270.nc") for f in check(STEPOVER)]
    assert found == [
        "O1270.nc:2:10: % inside a comment: a % starts and ends a transmission, so the "
        "control ends the program there and keeps only 'O1270 (10' of this block and no "
        "block after it (write PCT or the like instead)"
    ]
    said = [f.format("a.nc") for f in check("O1\nG0 X1 %\nM30\n")]
    assert said and said[0].startswith("a.nc:2:7: % inside a block:"), said


def test_diff_tells_a_copy_cut_at_a_percent_from_what_was_sent() -> None:
    # The control kept only what came before the %: that is a difference, not a match.
    result = compare(STEPOVER.encode(), b"O1270 (10\n")
    assert not result.same
    assert "-O1270 (10% STEPOVER)" in result.text and "+O1270 (10" in result.text
    # Framing, leader, trailer and CR still do not count.
    assert compare(b"\0\0%\r\nO1 (A)\r\nM30\r\n%\0\0", b"O1 (A)\nM30\n").same


async def test_a_percent_in_a_comment_is_refused_before_a_byte_goes_out(shop: Shop) -> None:  # noqa: F811
    program = ShopStore(shop.root).machine("mill1") / "programs" / "O1270.nc"
    program.write_text(STEPOVER)
    code, said = await finished(
        await cellctl("program", "check", "--kind", "iso-cnc", str(program))
    )
    assert code == 1 and ":2:10: % inside a comment" in said, said
    code, said = await finished(
        await cellctl("dnc", "check", "mill1", "O1270", "--dir", str(shop.root))
    )
    assert code == 1 and "the control ends the program there" in said, said
    assert "cellctl refuses to send it to mill1" in said, said
    code, said = await finished(
        await cellctl("dnc", "send", "mill1", "O1270", "--dir", str(shop.root))
    )
    assert code == 2 and "O1270:2:10: % inside a comment" in said, said
    assert shop.controls["mill1"].chars_read == 0 and 1270 not in shop.controls["mill1"].memory


async def test_dnc_diff_says_a_truncated_copy_differs(shop: Shop) -> None:  # noqa: F811
    store = ShopStore(shop.root)
    store.keep_sent("mill1", 1270, STEPOVER.encode())
    store.keep_received("mill1", 1270, b"O1270 (10\n")
    code, said = await finished(
        await cellctl("dnc", "diff", "mill1", "O1270", "--dir", str(shop.root))
    )
    assert code == 1, said
    assert "-O1270 (10% STEPOVER)" in said and "matches" not in said, said


async def test_dc1_timeout_ends_the_wait_for_a_read_nobody_starts(shop: Shop) -> None:  # noqa: F811
    toml = shop.root / "dnc.toml"
    toml.write_text(
        toml.read_text().replace(
            "[machines.mill1]\n", "[machines.mill1]\noptions = { dc1_timeout = 1 }\n"
        )
    )
    shop.controls["mill1"].set_fault("never-dc1")
    code, said = await finished(
        await cellctl("dnc", "send", "mill1", "O1234", "--dir", str(shop.root)), 60
    )
    assert code == 3, said
    assert "no DC1 (tape reader start) from the control in 1 s" in said, said
    log = "\n".join(ShopStore(shop.root).log_lines("mill1"))
    assert "O1234.nc: read in FAILED: mill1: no DC1" in log, log


def test_a_request_the_control_does_not_read_lapses_after_30_minutes(tmp_path: Path) -> None:
    async def main() -> tuple[str, float]:
        control = IsoCncEmulator(EmulatorOptions())
        server = await serve_mem(control, LINE, name="lapse-mill1")
        root = write_shop(tmp_path / "shop", {"mill1": server.url})
        store = ShopStore(root)
        (store.machine("mill1") / "programs" / "O1234.nc").write_text("O1234\nG0 X1\nM30\n")
        dnc = DncServer(load_shop(root))
        await dnc.start()
        clock = current_clock()
        try:
            control.memory[9999] = "O9999 (LOAD O1234)\n"
            control.set_mode(Mode.EDIT)
            control.punch(9999)
            while dnc.status()["mill1"].activity is not Activity.READING:
                await clock.sleep(1)  # the request taken, its answer waiting for READ
            asked = clock.monotonic()
            while not any("lapsed" in line for line in store.log_lines("mill1")):
                await clock.sleep(60)
                assert clock.monotonic() - asked < 2 * REQUEST_WAIT_S, store.log_lines("mill1")
            lapsed = next(line for line in store.log_lines("mill1") if "lapsed" in line)
            return lapsed, dnc.status()["mill1"].activity.value
        finally:
            await dnc.close()
            await server.close()

    lapsed, activity = run_virtual(main())
    assert "request load O1234 lapsed: the control did not read it within 30 minutes" in lapsed
    assert activity == "idle"


async def test_a_drip_feed_says_its_stall_in_wall_seconds_and_one_total(tmp_path: Path) -> None:
    control = IsoCncEmulator(EmulatorOptions(), time_scale=50)
    control.mode = Mode.RMT
    from cellctl.emulators.serve import serve

    server = await serve(control, "pty", LINE)
    root = write_shop(tmp_path / "shop", {"mill1": server.url}, "options = { motion_scale = 50 }\n")
    store = ShopStore(root)
    # Short fast segments: the line cannot keep up, the axes wait between blocks.
    rows = ["O5000 (SURFACE)", "G21 G90 G17", "G1 X0 Y0 F6000"]
    rows += [f"X{i * 0.1:.1f} Y{i % 2 * 0.1:.1f}" for i in range(1, 120)]
    (store.machine("mill1") / "programs" / "O5000.nc").write_text("\n".join([*rows, "M30"]) + "\n")
    dnc = DncServer(load_shop(root))
    await dnc.start()
    line = dnc.line("mill1")
    seen: list[tuple[str, int]] = []
    changed = line.changed

    def record() -> None:
        seen.append((line.status.phase, line.status.chars_total))
        changed()

    line.changed = record
    try:
        await until(lambda: line.driver is not None, "the link open")
        sending = asyncio.ensure_future(
            line.send("O5000.nc", store.program("mill1", 5000).read_bytes(), drip=True)
        )
        await until(lambda: line.status.phase == "waiting", "waiting for the read")
        control.cycle_start()
        async with current_clock().timeout(120):
            result = await sending
    finally:
        await dnc.close()
        await server.close()
    found = re.search(r"in ([\d.]+) s .*, stalled ([\d.]+) s", result["message"])
    assert found, result["message"]
    elapsed, stalled = float(found.group(1)), float(found.group(2))
    assert 0 < stalled <= elapsed, result["message"]  # a wait no longer than the drip-feed
    # "preparing" says no total; from "waiting" on, one total: the tape's, never the file's.
    assert seen[0][0] == "preparing", seen
    totals = {total for phase, total in seen if phase in ("waiting", "sending", "stopped")}
    assert len(totals) == 1, seen


def test_colon_for_o_padding_after_the_tape_and_one_problem_a_block() -> None:
    # `:` is the program number's address where a control writes it so (spec).
    assert check(":1247 (BRACKET)\nG0 X1\nM30\n") == []
    # A DOS file's Ctrl-Z and NULs after the closing %: the control never reads past it.
    assert check("%\nO1\nG0 X1\nM30\n%\n\x1a\x00\x00") == []
    # One problem a block, not one a character.
    nested = [f.format("p") for f in check("O1\nG0 X1 (a (b (c\nM30\n")]
    assert nested == ["p:2:10: ( inside a comment (they do not nest)"]
    macro = [f.format("p") for f in check("O1\n#1=[#2+1]\nM30\n")]
    assert len(macro) == 1 and "'#' is not part of a word (macro B" in macro[0], macro


async def test_a_program_number_is_said_back_as_written(shop: Shop) -> None:  # noqa: F811
    code, said = await finished(
        await cellctl("dnc", "send", "mill1", "O1", "--dir", str(shop.root))
    )
    assert code == 2 and "no program O1 in " in said and "O0001" not in said, said
    code, said = await finished(
        await cellctl("dnc", "diff", "mill1", "O1", "--dir", str(shop.root))
    )
    assert code == 2 and "no O1 received from mill1" in said and "O0001" not in said, said
