"""The console on a shop served by ``cellctl dnc serve`` (no cell): driven with Textual's
Pilot at 80x24, attached to a DNC server running in this process (its API on the shop's
socket) that feeds emulated ISO-code controls over a pty and TCP; and in a real terminal
(tmux), the installed ``cellctl console --dir SHOP`` on a ``cellctl dnc serve`` process
feeding a ``cellctl emulate iso-cnc`` process.

The main menu has each DNC machine and EXIT (no robot, no CELL menu); a machine's menu is
the server's (READ IN, DRIP FEED, RECEIVE PUNCH, STOP TRANSFER, LOG); the board shows each
machine's activity, its progress in characters (rate, time left) and its stall time, live.
Assertions are on the screen, the emulated controls and the shop's own records.
"""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from textual.pilot import Pilot
from textual.widgets import Static

from cellctl.emulators.serve import Server, serve
from cellctl.errors import CellctlError
from cellctl.kinds.iso_cnc.dnc.cli import serve_shop
from cellctl.kinds.iso_cnc.dnc.config import load_shop
from cellctl.kinds.iso_cnc.dnc.store import ShopStore
from cellctl.kinds.iso_cnc.emulator import EmulatorOptions, IsoCncEmulator, Mode
from cellctl.link import LineSettings
from cellctl.service.client import RemoteCell, attach
from cellctl.service.token import TOKEN_ENV, add_token
from cellctl.ui.console.app import ConsoleApp
from cellctl.ui.console.served import parse_served
from tests.conftest import CELLCTL, emulator_process, until
from tests.test_console import SIZE, fill, screen_text, wait_text
from tests.test_console_tmux import Tmux, stop, tmux, wait_until

__all__ = ["tmux"]  # the fixture, used by name

LINE = LineSettings.parse("9600,7E2")
BRACKET = "O1234 (BRACKET)\nG21 G90 G17\nG00 X0 Y0 Z5.\nG01 Z-1. F300\nG01 X10. Y5.\nM30\n"


def surfacing(moves: int) -> str:
    """A drip-feed program of 0.1 mm moves: the machine eats them faster than 9600 baud
    brings them (so it stalls), over a few seconds of line time."""
    rows = [f"X{i / 10:.1f} Y{i % 2 / 10:.1f}\n" for i in range(1, moves + 1)]
    return "O5000 (SURFACE)\nG21 G90 G17\nG01 X0 Y0 F3000\n" + "".join(rows) + "M30\n"


DRIP = surfacing(400)


@dataclass
class Shop:
    root: Path
    controls: dict[str, IsoCncEmulator]


@pytest.fixture
async def shop(tmp_path: Path) -> AsyncIterator[Shop]:
    """Two controls (mill1 on a pty, mill2 on TCP) fed by a DNC server running here."""
    controls = {"mill1": IsoCncEmulator(EmulatorOptions()), "mill2": IsoCncEmulator()}
    servers: list[Server] = [
        await serve(controls["mill1"], "pty", LINE),
        await serve(controls["mill2"], "socket://127.0.0.1:0", LINE),
    ]
    root = tmp_path / "shop"
    root.mkdir()
    rows = [
        f'[machines.{name}]\nlink = "{server.url}"\n'
        for name, server in zip(controls, servers, strict=True)
    ]
    (root / "dnc.toml").write_text("\n".join(rows))
    store = ShopStore(root)
    for name in controls:
        (store.machine(name) / "programs" / "O1234.nc").write_text(BRACKET)
        (store.machine(name) / "programs" / "O5000.nc").write_text(DRIP)
    stop = asyncio.Event()
    task = asyncio.create_task(serve_shop(load_shop(root), stop=stop))
    try:
        await until(lambda: task.done() or (root / "api.sock").exists(), "the shop's API")
        assert not task.done(), task.exception()
        yield Shop(root, controls)
    finally:
        stop.set()
        await task
        for server in servers:
            await server.close()


async def console(shop: Shop) -> tuple[ConsoleApp, RemoteCell]:
    client = await attach(shop.root)
    return ConsoleApp(shop.root, client, traffic_period=0.1), client


async def wait_screen(
    pilot: Pilot[Any], pattern: str, what: str, timeout: float = 30.0, flags: int = 0
) -> re.Match[str]:
    """Wait until the screen matches ``pattern`` (a regex); fail with the screen otherwise."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        await pilot.pause(0.02)
        shown = screen_text(pilot.app)  # type: ignore[arg-type]
        found = re.search(pattern, shown, flags)
        if found is not None:
            return found
        if loop.time() > deadline:
            raise AssertionError(f"not on screen: {what}\n{shown}")


async def start_drip(pilot: Pilot[Any], machine_key: str, program: str) -> None:
    """Main menu -> the machine's menu -> 2 DRIP FEED -> the program, OK."""
    await pilot.press(machine_key)
    await wait_text(pilot, "2. DRIP FEED")
    await pilot.press("2")
    await wait_text(pilot, "Program file:")
    await fill(pilot, "#program", program)
    await pilot.click("#ok")


async def test_the_shop_s_machines_and_their_menus(shop: Shop) -> None:
    app, client = await console(shop)
    async with app.run_test(size=SIZE) as pilot:
        shown = await wait_text(pilot, "MAIN MENU", "attached to DNC shop (pid", "3. EXIT")
        menu = [line[:36].strip() for line in shown.splitlines()[2:12]]
        assert [m for m in menu if m] == [
            "1. NC MACHINE #1 (mill1)",
            "2. NC MACHINE #2 (mill2)",
            "3. EXIT",
        ], shown
        assert "ROBOT" not in shown and "CELL (orders" not in shown
        assert re.search(r"mill1\s+idle\s+idle", shown) and re.search(r"mill2\s+idle", shown)
        await pilot.press("c")  # no CELL menu on a shop: the key does nothing
        await pilot.press("1")
        shown = await wait_text(pilot, "NC MACHINE #1 (mill1)", "6. EXIT")
        menu = [line[:36].strip() for line in shown.splitlines()[2:12]]
        assert [m for m in menu if m] == [
            "1. READ IN",
            "2. DRIP FEED",
            "3. RECEIVE PUNCH",
            "4. STOP TRANSFER",
            "5. LOG",
            "6. EXIT",
        ], shown
        # READ IN: O1234 into mill1's memory, the operator presses READ (EDIT mode).
        await pilot.press("1")
        await wait_text(pilot, "Program file:")
        await fill(pilot, "#program", "mill1/programs/O1234.nc")
        await pilot.click("#ok")
        await wait_screen(pilot, r"mill1\s+busy\s+reading O1234\.nc", "mill1 reading")
        shop.controls["mill1"].read()
        await wait_text(pilot, "mill1: READ IN: O1234.nc: read in, ", timeout=30)
        assert shop.controls["mill1"].memory[1234] == BRACKET
        await wait_screen(pilot, r"mill1\s+idle", "mill1 idle again")
        # Its traffic, both ways (the server keeps each machine's last bytes).
        await wait_text(pilot, "traffic: mill1", ">> ", "<< ")
        # LOG: the machine's log, through the API.
        await pilot.press("5")
        await wait_text(pilot, "mill1: LOG: the last ", "O1234.nc: read in")
        await pilot.press("6")
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("q")
    await client.close()


async def test_a_drip_feed_s_progress_and_stall_on_the_board(shop: Shop) -> None:
    control = shop.controls["mill2"]
    app, client = await console(shop)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await start_drip(pilot, "2", "mill2/programs/O5000.nc")
        # Waiting for the control's CYCLE START: shown with none of the characters sent.
        await wait_screen(pilot, r"mill2\s+busy\s+drip-feeding O5000\.nc", "mill2 drip-feeding")
        total = len(DRIP)
        await wait_screen(pilot, r"\b0/\d+ chars waiting", "waiting for its CYCLE START")
        control.set_mode(Mode.RMT)
        control.cycle_start()
        # Under way: some of the characters, a rate and the stall time on the board.
        found = await wait_screen(pilot, r"\b([1-9]\d*)/(\d+) chars", "characters under way")
        assert int(found.group(1)) < int(found.group(2)) and int(found.group(2)) >= total
        # The machine waits for blocks the line has not brought yet: its stall time grows.
        stall = r"\d+ chars/s\b.*stall (?!0\.0)\d+\.\d s"
        await wait_screen(pilot, stall, "its rate and a stall time")
        # Done: the server's message with the stall in all, and the machine idle again.
        done = r"mill2: DRIP FEED: O5000\.nc: drip-fed, .*?stalled\s+(?!0\.0)\d+\.\d s"
        await wait_screen(pilot, done, "the drip-feed's end", timeout=60, flags=re.S)
        await wait_screen(pilot, r"mill2\s+idle", "mill2 idle again")
        await until(lambda: control.runs and control.runs[-1].done, "the run's end")
        assert control.runs[-1].blocks == DRIP.count("\n") and not control.alarms
        await pilot.press("q")
    await client.close()
    log = "\n".join(ShopStore(shop.root).log_lines("mill2"))
    assert "O5000.nc: drip-fed" in log


async def program_dialog(pilot: Pilot[Any], key: str) -> str:
    """From the main menu, machine 1's function ``key`` (1 READ IN, 2 DRIP FEED) to its
    program dialog, its picker listing both machines' folders: the screen."""
    await wait_text(pilot, "MAIN MENU")
    await pilot.press("1")
    await wait_text(pilot, "1. READ IN", "2. DRIP FEED")
    await pilot.press(key)
    return await wait_text(pilot, "Program file:", "mill1", "mill2")


async def test_the_program_picker_shows_no_private_directory(shop: Shop) -> None:
    """The DNC file picker browses the shop for programs, never its tokens or locks."""
    (shop.root / "tokens").mkdir(mode=0o700, exist_ok=True)
    app, client = await console(shop)
    async with app.run_test(size=SIZE) as pilot:
        shown = await program_dialog(pilot, "2")
        assert "tokens" not in shown and "state" not in shown, shown
        await pilot.click("#cancel")
        await pilot.press("q")
    await client.close()


async def enter_in(pilot: Pilot[Any], selector: str) -> None:
    """Enter in a dialog's field, as a user types it (its OK): a click computed from a layout
    the last refusal was still changing could land beside OK (it did, now and then)."""
    pilot.app.screen.query_one(selector).focus()
    await pilot.press("enter")


async def test_the_program_picker_reads_nothing_outside_the_shop(
    shop: Shop, tmp_path: Path
) -> None:
    """A program outside the shop (its path, a ``..``, a symlink to it or to its folder) is
    refused in the dialog before it is read, nothing sent; a folder leading out is not
    listed. A symlink within the shop is taken."""
    outside = tmp_path / "camout"
    outside.mkdir()
    (outside / "O1234.nc").write_text(BRACKET)
    (shop.root / "camout").symlink_to(outside)  # a folder leading out
    programs = shop.root / "mill1" / "programs"
    (programs / "O4321.nc").symlink_to(outside / "O1234.nc")  # a file leading out
    (programs / "O1234 same.nc").symlink_to(programs / "O1234.nc")  # within: taken
    app, client = await console(shop)
    async with app.run_test(size=SIZE) as pilot:
        shown = await program_dialog(pilot, "1")
        assert "camout" not in shown, shown

        def refusal() -> str:  # the dialog's words (none once it has gone)
            found = app.screen.query("#errors")
            return str(found.first(Static).content) if found else ""

        for given in (
            str(outside / "O1234.nc"),
            "../camout/O1234.nc",
            "camout/O1234.nc",
            "mill1/programs/O4321.nc",
        ):
            await fill(pilot, "#program", given)
            await enter_in(pilot, "#program")
            await until(
                lambda g=given: refusal().startswith(f"{g}: not in the shop"), f"{given} refused"
            )
            assert "program picker reads only files under the shop" in refusal()
        assert shop.controls["mill1"].chars_read == 0
        assert not any(" by hand" in x for x in ShopStore(shop.root).log_lines("mill1"))
        await fill(pilot, "#program", "mill1/programs/O1234 same.nc")
        await enter_in(pilot, "#program")
        await wait_screen(pilot, r"mill1\s+busy\s+reading O1234 same", "mill1 reading it")
        await pilot.press("4", "y")  # STOP TRANSFER: nothing went out yet
        await wait_screen(pilot, r"mill1\s+idle", "mill1 idle after the stop")
        await pilot.press("q")
    await client.close()


async def test_a_binary_program_is_refused_in_the_words_of_the_command_line(shop: Shop) -> None:
    """One refusal of a file that is not ISO code, whether the console's picker or
    ``cellctl dnc send`` reads it: the same words after the file's name."""
    binary = shop.root / "mill1" / "programs" / "O7777.nc"
    binary.write_bytes(b"%\nO7777\nG21 (D\xc9BUT)\nM30\n%\n")
    code, cli = await cellctl_run("dnc", "send", "mill1", "O7777", "--dir", str(shop.root))
    assert code == 2, cli
    cli_words = " ".join(cli.split()).split(f"{binary}: ", 1)[-1]
    assert "byte 15 " in cli_words and "0xC9" in cli_words, cli
    app, client = await console(shop)
    async with app.run_test(size=SIZE) as pilot:
        await program_dialog(pilot, "1")
        await fill(pilot, "#program", "mill1/programs/O7777.nc")
        await pilot.click("#ok")
        errors = app.screen.query_one("#errors", Static)
        await until(lambda: str(errors.content), "the dialog's refusal")
        assert str(errors.content) == f"mill1/programs/O7777.nc: {cli_words}", cli
        assert "not ISO code: byte 15 is 0xC9 (a program is 7-bit ASCII)" in cli_words
        await pilot.click("#cancel")
        await pilot.press("q")
    await client.close()
    assert shop.controls["mill1"].chars_read == 0


async def test_only_the_operator_s_own_transfer_is_marked_in_the_traffic(shop: Shop) -> None:
    """``>>*`` marks the first bytes of the operator's own command: not those of a
    ``cellctl dnc send`` started after a command of the console that sent nothing (LOG)."""
    control = shop.controls["mill1"]
    own = r"\d\d:\d\d:\d\d\.\d{3} >>\* "
    app, client = await console(shop)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("1")
        await wait_text(pilot, "5. LOG", "traffic: mill1")
        await pilot.press("5")  # the console's command: it sends nothing to the control
        await wait_text(pilot, "mill1: LOG: ")
        sent = asyncio.create_task(
            cellctl_run("dnc", "send", "mill1", "O1234", "--dir", str(shop.root))
        )
        await wait_screen(pilot, r"mill1\s+busy\s+reading O1234\.nc", "the CLI's read-in")
        control.read()
        code, said = await sent
        assert code == 0, said
        await wait_screen(pilot, r"\d{3} >>[ *] ", "the CLI's bytes on the traffic pane")
        await pilot.pause(0.5)  # a few more looks at the traffic
        assert not re.search(own, screen_text(app)), screen_text(app)
        # The operator's own READ IN: its first bytes marked as theirs.
        await pilot.press("1")
        await wait_text(pilot, "Program file:")
        await fill(pilot, "#program", "mill1/programs/O1234.nc")
        await pilot.click("#ok")
        await wait_screen(pilot, r"mill1\s+busy\s+reading O1234\.nc", "the console's read-in")
        control.read()
        await wait_text(pilot, "mill1: READ IN: O1234.nc: read in, ", timeout=30)
        await wait_screen(pilot, own, "the operator's own bytes marked")
        await pilot.press("q")
    await client.close()


async def test_stop_transfer_ends_a_drip_feed_in_flight(shop: Shop) -> None:
    control = shop.controls["mill1"]
    app, client = await console(shop)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await start_drip(pilot, "1", "mill1/programs/O5000.nc")
        await wait_screen(pilot, r"mill1\s+busy\s+drip-feeding O5000\.nc", "mill1 drip-feeding")
        control.set_mode(Mode.RMT)
        control.cycle_start()
        await wait_screen(pilot, r"\b[1-9]\d*/\d+ chars", "characters under way")
        await pilot.press("4")  # STOP TRANSFER, confirmed
        await wait_text(pilot, "Stop the transfer in flight")
        await pilot.press("y")
        await wait_text(pilot, "stopped by hand: the drip-feed of O5000.nc ended at ")
        await wait_screen(pilot, r"mill1\s+idle", "mill1 idle after the stop")
        # Ended the clean way: the rest of a block, then %: the control ran what it held
        # and left the read, no alarm, nothing to reset.
        await until(lambda: control.activity == "idle", "the control out of its read")
        assert control.runs[-1].done and not control.alarms
        # Nothing in flight now: the server says so, in its words.
        await pilot.press("4", "y")
        await wait_text(pilot, "mill1: STOP TRANSFER: mill1: nothing to stop")
        await pilot.press("q")
    await client.close()
    log = "\n".join(ShopStore(shop.root).log_lines("mill1"))
    assert "stopped by hand: the drip-feed of O5000.nc ended at" in log


async def test_receive_punch_keeps_what_the_control_punches(shop: Shop) -> None:
    control = shop.controls["mill1"]
    edited = BRACKET.replace("X10. Y5.", "X12. Y5.")
    app, client = await console(shop)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("1")
        await wait_text(pilot, "3. RECEIVE PUNCH")
        await pilot.press("3")
        await wait_screen(pilot, r"mill1\s+idle\s+waiting for punch", "mill1 waiting for it")
        control.memory[1234] = edited  # edited at the machine, punched back
        control.set_mode(Mode.EDIT)
        control.punch(1234)
        await wait_text(pilot, "mill1: RECEIVE PUNCH: received O1234 (")
        await wait_screen(pilot, r"mill1\s+idle\s+idle", "mill1 idle again")
        await pilot.press("q")
    await client.close()
    kept = ShopStore(shop.root).received("mill1", 1234)
    assert [k.path.read_text() for k in kept] == [edited]


async def test_a_viewer_token_is_refused_an_action_with_the_api_s_words(
    shop: Shop, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(TOKEN_ENV, add_token(shop.root, "ann", "viewer"))
    app, client = await console(shop)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU", "mill1")
        await start_drip(pilot, "1", "mill1/programs/O5000.nc")
        await wait_text(pilot, "mill1: DRIP FEED: ann is a viewer: dnc.send needs the operator")
        # A viewer still watches: the log is a read.
        await pilot.press("5")
        await wait_text(pilot, "mill1: LOG: ")
        await pilot.press("q")
    await client.close()
    assert shop.controls["mill1"].chars_read == 0  # nothing went to the control


async def test_a_wrong_token_is_refused_before_the_console_starts(shop: Shop) -> None:
    env = {**os.environ, TOKEN_ENV: "x" * 43}
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL,
        "console",
        "--dir",
        str(shop.root),
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env=env,
    )
    async with asyncio.timeout(60):
        out, err = await proc.communicate()
    said = out.decode() + err.decode()
    assert proc.returncode != 0, said
    assert f"$CELLCTL_TOKEN is no token of {shop.root} (wrong or revoked)" in said, said
    assert "Traceback" not in said


def test_console_on_a_directory_with_no_cell_and_no_server(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from cellctl.ui.cli import main

    result = CliRunner().invoke(main, ["console", "--dir", str(tmp_path)])
    assert result.exit_code == 2, result.output
    assert "no cell in" in result.output and "no server runs there" in result.output


def test_console_in_a_terminal_watches_a_drip_feed(tmux: Tmux, tmp_path: Path) -> None:
    """80x24, every process its own: the operator drip-feeds O5000 from the console; the
    board shows mill1 drip-feeding with its characters, rate and stall time growing, then
    idle again with the server's message."""
    env = {**os.environ, "NO_COLOR": "1"}
    with emulator_process("iso-cnc", "--mode", "rmt", "--auto-operator") as url:
        root = tmp_path / "shop"
        root.mkdir()
        (root / "dnc.toml").write_text(f'[machines.mill1]\nlink = "{url}"\n')
        (ShopStore(root).machine("mill1") / "programs" / "O5000.nc").write_text(DRIP)
        server = subprocess.Popen(
            [*CELLCTL, "dnc", "serve", "--dir", str(root)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )
        try:
            wait_until(lambda: (root / "api.sock").exists(), "the DNC server's API socket")
            tmux.start([*CELLCTL, "console", "--dir", str(root)], {"TERM": "xterm-256color"})
            shown = tmux.wait_for("MAIN MENU", "attached to DNC shop (pid", "2. EXIT")
            assert "1. NC MACHINE #1 (mill1)" in shown and "CELL" not in shown, shown
            assert re.search(r"mill1\s+idle\s+idle", shown), shown
            tmux.keys("1")
            tmux.wait_for("NC MACHINE #1 (mill1)", "2. DRIP FEED", "6. EXIT")
            tmux.keys("2")
            tmux.wait_for("Program file:")
            tmux.keys("-l", "mill1/programs/O5000.nc")
            tmux.wait_for("mill1/programs/O5000.nc")
            tmux.keys("Enter")
            # The control (in RMT, its operator pressing CYCLE START) takes it block by block.
            seen: list[tuple[int, float]] = []

            def under_way() -> bool:
                screen = tmux.screen()
                chars = re.search(r"\b(\d+)/(\d+) chars", screen)
                stalled = re.search(r"chars/s\b.*stall (\d+\.\d) s", screen)
                if "drip-feeding O5000.nc" in screen and chars and stalled:
                    done, total = int(chars.group(1)), int(chars.group(2))
                    if 0 < done < total and (not seen or seen[-1][0] != done):
                        seen.append((done, float(stalled.group(1))))
                return len(seen) >= 2

            wait_until(under_way, "the drip-feed's progress moving on the board")
            assert seen[1][0] > seen[0][0] and seen[1][1] >= seen[0][1], seen
            shown = tmux.wait_for("mill1: DRIP FEED: O5000.nc: drip-fed, ", timeout=60)
            wait_until(
                lambda: re.search(r"mill1\s+idle", tmux.screen()) is not None, "mill1 idle again"
            )
            tmux.keys("q")
            wait_until(tmux.pane_dead, "the console to quit")
        finally:
            stop(server)


async def cellctl_run(*args: str) -> tuple[int, str]:
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL,
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env={**os.environ, "COLUMNS": "200"},
    )
    async with asyncio.timeout(60):
        out, err = await proc.communicate()
    return proc.returncode or 0, out.decode() + err.decode()


async def state_is(state: Callable[[], Awaitable[str]], prefix: str) -> bool:
    return (await state()).startswith(prefix)


async def test_dnc_stop_by_hand_ends_a_drip_started_through_the_api(shop: Shop) -> None:
    """``cellctl dnc stop`` through the running server: the drip-feed's caller (here a
    script on the API) gets the stop, in the server's words; nothing in flight is refused."""
    control = shop.controls["mill2"]
    control.set_mode(Mode.RMT)
    async with await attach(shop.root) as api:

        async def machine() -> dict[str, Any]:
            status: dict[str, Any] = await api.call("cell.status")
            return status

        drip = asyncio.create_task(
            api.call("dnc.send", {"machine": "mill2", "program": "O5000", "drip": True})
        )

        async def state() -> str:
            return str((await machine())["machines"]["mill2"]["state"])

        await until(lambda: state_is(state, "drip-feeding O5000.nc"), "mill2 drip-feeding")
        control.cycle_start()

        async def under_way() -> bool:
            progress = (await machine())["machines"]["mill2"]["progress"] or {}
            return 0 < int(progress.get("done", 0)) < int(progress.get("total", 0))

        await until(under_way, "the drip-feed under way")
        code, said = await cellctl_run("dnc", "stop", "mill2", "--dir", str(shop.root))
        assert code == 0, said
        assert "stopped by hand: the drip-feed of O5000.nc ended at " in said
        with pytest.raises(CellctlError, match=r"stopped by hand: the drip-feed of O5000\.nc"):
            await drip
        status = (await machine())["machines"]["mill2"]
        assert status["condition"] == "idle" and status["progress"] is None
        control.reset()
        code, said = await cellctl_run("dnc", "stop", "mill2", "--dir", str(shop.root))
        assert code == 0 and "mill2: nothing to stop: no transfer in flight" in said, said


JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=20,
)
FUNCTION = st.fixed_dictionaries(
    {
        "key": st.sampled_from(["1", "9", "a", "z", "", "10", "A", "!"]) | st.text(max_size=2),
        "label": st.sampled_from(["READ IN", ""]) | st.text(max_size=50),
        "method": st.sampled_from(["dnc.send", ""]) | st.text(max_size=20),
    },
    optional={"params": JSON, "asks": JSON, "confirm": JSON, "timeout_s": JSON},
)


@given(st.one_of(JSON, st.dictionaries(st.text(max_size=8), st.lists(FUNCTION, max_size=3))))
@settings(max_examples=200, deadline=None)
def test_any_served_menu_is_a_menu_or_a_refusal(raw: object) -> None:
    """Whatever a server answers to machines.functions: menus of checked functions, or a
    CellctlError saying so (the console then does not start: one line, an exit code)."""
    try:
        menus = parse_served(raw)
    except CellctlError as e:
        assert "machines.functions" in str(e)
        return
    for functions in menus.values():
        for fn in functions:
            assert len(fn.key) == 1 and fn.label and fn.method and fn.timeout_s > 0
