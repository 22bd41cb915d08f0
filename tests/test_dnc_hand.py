"""``cellctl dnc`` by hand, where a user's script or a second terminal meets it: which file an
O-number means, the command a busy refusal suggests (run as printed), the exit code of a
transfer stopped before its end, ``dnc check``'s exit code, and ``dnc stop`` of a transfer
that a ``dnc drip`` runs on its own link (no server). Real processes against emulated
controls over a pty and TCP."""

from __future__ import annotations

import asyncio
import contextlib
import re
import shlex
import signal
from collections.abc import AsyncIterator
from pathlib import Path

from cellctl.drivers.state import StateStore
from cellctl.kinds.iso_cnc.dnc.store import ShopStore
from cellctl.kinds.iso_cnc.emulator import Mode
from cellctl.kinds.iso_cnc.status import IsoCncState
from tests.conftest import until
from tests.test_dnc_cli import (  # noqa: F401  (shop and served are fixtures)
    BRACKET,
    Shop,
    cellctl,
    finished,
    served,
    shop,
    wait_state,
)
from tests.test_dnc_server import surfacing
from tests.test_dnc_stop import MOVES, run_here

COPY = BRACKET.replace("X10. Y5.", "X99. Y5.")  # the copy, edited


async def test_an_exact_name_wins_and_two_candidates_are_refused(shop: Shop) -> None:  # noqa: F811
    root = str(shop.root)
    programs = ShopStore(shop.root).machine("mill1") / "programs"
    (programs / "O1234 copy.nc").write_text(COPY)
    code, said = await run_here("dnc", "check", "mill1", "O1234", "--dir", root)
    assert code == 0, said
    assert "O1234 (O1234.nc) for mill1" in said, said
    # `dnc send` sends O1234.nc, not the copy
    control = shop.controls["mill1"]
    sending = await cellctl("dnc", "send", "mill1", "O1234", "--dir", root)
    store = StateStore(shop.root)  # no server: the command holds the link itself
    await until(lambda: store.load("mill1").get("state") == IsoCncState.READING, "the send", 30)
    control.read()  # the operator presses READ
    code, said = await finished(sending)
    assert code == 0, said
    assert "O1234.nc: read in" in said
    assert control.memory[1234] == BRACKET
    # Without O1234.nc, two files start with O1234: which one is meant cannot be guessed.
    (programs / "O1234.nc").unlink()
    (programs / "O1234 bracket.nc").write_text(BRACKET)
    before = control.chars_read
    for command in ("check", "send", "drip"):
        code, said = await run_here("dnc", command, "mill1", "O1234", "--dir", root)
        assert code == 2, (command, said)
        assert "O1234 is ambiguous" in said, said
        assert "'O1234 bracket.nc'" in said and "'O1234 copy.nc'" in said, said
        assert "start with it and none is O1234.nc" in " ".join(said.split()), said
    assert control.chars_read == before  # nothing went out
    # Two files named by the number alone: the same refusal, in their own words.
    (programs / "O1234.nc").write_text(BRACKET)
    (programs / "O1234.tap").write_text(BRACKET)
    code, said = await run_here("dnc", "check", "mill1", "O1234", "--dir", root)
    assert code == 2 and "are each named by it alone" in " ".join(said.split()), said
    (programs / "O1234.nc").unlink()
    (programs / "O1234.tap").unlink()
    # One file alone, whatever its ending, is the program.
    (programs / "O1234 copy.nc").unlink()
    code, said = await run_here("dnc", "check", "mill1", "O1234", "--dir", root)
    assert code == 0 and "O1234 (O1234 bracket.nc)" in said, said


async def test_a_wrong_o_number_is_a_problem_check_exits_1(shop: Shop) -> None:  # noqa: F811
    programs = ShopStore(shop.root).machine("mill1") / "programs"
    (programs / "O1111.nc").write_text(BRACKET)  # its text is O1234
    code, said = await run_here("dnc", "check", "mill1", "O1111", "--dir", str(shop.root))
    assert code == 1, said
    assert "its name says O1111 but its text is O1234" in said
    assert "1 problem(s): cellctl refuses to send it to mill1" in said
    # `send` refuses it before a byte goes out, as bad input (2)
    code, said = await run_here("dnc", "send", "mill1", "O1111", "--dir", str(shop.root))
    assert code == 2 and "its name says O1111" in said, said
    assert shop.controls["mill1"].chars_read == 0


async def test_the_busy_refusal_suggests_a_stop_that_works_as_printed(served: Shop) -> None:  # noqa: F811
    root = str(served.root)
    first = await cellctl("dnc", "send", "mill1", "O1234", "--dir", root)
    await wait_state(served, "mill1", "reading O1234.nc")
    code, said = await finished(await cellctl("dnc", "send", "mill1", "O1234", "--dir", root))
    assert code == 6, said
    found = re.search(r"stop it with `([^`]*)`", said)
    assert found is not None, said
    printed = found.group(1)
    assert f"--dir {shlex.quote(str(served.root.absolute()))}" in printed, printed
    # run as printed: it stops the read-in; the stopped send exits 130, saying so
    code, said = await finished(await cellctl(*shlex.split(printed)[1:]))
    assert code == 0, said
    assert "stopped by hand: the read-in of O1234.nc was cancelled" in said, said
    code, said = await finished(first)
    assert code == 130, said
    assert "stopped by hand: the read-in of O1234.nc was cancelled" in said, said
    assert served.controls["mill1"].chars_read == 0


@contextlib.asynccontextmanager
async def hand_drip(shop: Shop, program: Path) -> AsyncIterator[asyncio.subprocess.Process]:  # noqa: F811
    """`cellctl dnc drip mill2 PROGRAM` with no server (the command holds the link itself),
    begun: the control in RMT and CYCLE START pressed once it waits. Killed if still running
    on the way out."""
    control = shop.controls["mill2"]
    control.set_mode(Mode.RMT)
    drip = await cellctl("dnc", "drip", "mill2", str(program), "--dir", str(shop.root))
    try:
        store = StateStore(shop.root)
        await until(
            lambda: store.load("mill2").get("state") == IsoCncState.DRIP_FEEDING,
            "the drip-feed waiting for the control",
            30,
        )
        control.cycle_start()
        yield drip
    finally:
        if drip.returncode is None:
            drip.kill()
            await finished(drip)


async def test_dnc_stop_ends_a_drip_feed_run_by_hand_without_a_server(
    shop: Shop,  # noqa: F811
    tmp_path: Path,
) -> None:
    root = str(shop.root)
    program = tmp_path / "surface.nc"
    program.write_text(surfacing(MOVES))
    control = shop.controls["mill2"]
    async with hand_drip(shop, program) as drip:
        await until(lambda: control.chars_read > 200, "the drip-feed under way", 30)
        # A second transfer: busy, and the stop it suggests is one that works
        code, said = await run_here("dnc", "drip", "mill2", str(program), "--dir", root)
        assert code == 6, said
        assert "mill2 is busy: cellctl dnc drip mill2 (pid " in said, said
        assert f"stop it with `cellctl dnc stop mill2 --dir {shop.root.absolute()}`" in said
        assert "cellctl console" not in said
        code, said = await finished(await cellctl("dnc", "stop", "mill2", "--dir", root))
        assert code == 0, said
        assert "stopped by hand: the drip-feed of surface.nc ended at " in said, said
        code, told = await finished(drip, 30)
        assert code == 130, told
        assert "stopped by hand: the drip-feed of surface.nc ended at " in told, told
    # ended as the spec ends a tape: the control ran what it held and left the read
    await until(lambda: control.activity == "idle", "the control out of its read")
    assert control.runs[-1].done and not control.alarms
    assert control.runs[-1].blocks < MOVES
    log = "\n".join(ShopStore(shop.root).log_lines("mill2"))
    assert "stopped by hand: the drip-feed of surface.nc ended at" in log


async def test_dnc_stop_refuses_a_hand_command_that_is_no_transfer(shop: Shop) -> None:  # noqa: F811
    root = str(shop.root)
    control = shop.controls["mill2"]
    receiver = await cellctl("dnc", "receive", "mill2", "--timeout", "60", "--dir", root)
    try:
        assert receiver.stderr is not None  # its prompt: it holds the link and listens
        async with asyncio.timeout(30):
            prompt = await receiver.stderr.readline()
        assert b"press PUNCH" in prompt, prompt
        code, said = await run_here("dnc", "stop", "mill2", "--dir", root)
        assert code == 6, said
        assert "in use by cellctl dnc receive mill2 (pid " in said, said
        assert "Ctrl-C in its terminal" in said and "cellctl console" not in said, said
        assert receiver.returncode is None  # not signalled: it still waits for the punch
        control.memory[5000] = "O5000\nG00 X0\nM30\n"
        control.punch(5000)
        code, said = await finished(receiver)
        assert code == 0 and "received O5000" in said, said
    finally:
        if receiver.returncode is None:
            receiver.send_signal(signal.SIGINT)
            await finished(receiver)


async def test_dnc_stop_when_all_of_a_hand_drip_feed_is_out_changes_nothing(
    shop: Shop,  # noqa: F811
    tmp_path: Path,
) -> None:
    """docs/dnc.md: a stop that came when all of the program was out changes nothing (0).
    The control holds the whole of a short, slow program in its buffer: `dnc stop` says so at
    once, and the drip-feed ends by itself, 0, logged as drip-fed."""
    root = str(shop.root)
    program = tmp_path / "slow.nc"
    program.write_text("O5001 (SLOW)\nG21 G90 G17\nG01 X0 Y0 F3000\nG01 X6. F60\nM30\n")
    control = shop.controls["mill2"]
    async with hand_drip(shop, program) as drip:
        await until(lambda: control.runs and control.runs[-1].blocks >= 3, "the slow move", 30)
        assert not control.runs[-1].done
        code, said = await finished(await cellctl("dnc", "stop", "mill2", "--dir", root))
        assert code == 0, said
        assert "all of the drip-feed of slow.nc is out: the control runs the rest" in said, said
        code, told = await finished(drip, 60)
        assert code == 0, told
        assert "drip-fed" in told, told
    assert control.runs[-1].done and not control.alarms
    log = "\n".join(ShopStore(shop.root).log_lines("mill2"))
    assert "is out: the control runs the rest" in log and "slow.nc: drip-fed" in log, log
