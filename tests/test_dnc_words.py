"""What ``cellctl dnc`` says where a user reads it: a request program the control cannot
number (refused when dnc.toml is loaded), program numbers out of the control's range, the
character counts of a read-in (the program, the tape on the line), the state while a program
waits for the operator's read, a zero feed, and a machine whose link is down. Real processes
and the CLI against emulated controls over a pty and TCP; the G-code check's words direct."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from cellctl.drivers.state import StateStore
from cellctl.errors import UsageError
from cellctl.kinds.iso_cnc import gcode
from cellctl.kinds.iso_cnc.dnc.config import load_shop
from cellctl.kinds.iso_cnc.dnc.request import Request, parse_request
from cellctl.kinds.iso_cnc.dnc.store import ShopStore
from cellctl.kinds.iso_cnc.emulator import Mode
from cellctl.kinds.iso_cnc.status import IsoCncState
from cellctl.kinds.iso_cnc.tape import unframe
from tests.conftest import refusing_port, until
from tests.test_dnc_cli import (  # noqa: F401  (shop and served are fixtures)
    Shop,
    cellctl,
    finished,
    served,
    shop,
    wait_state,
)
from tests.test_dnc_stop import run_here

DOCS = Path(__file__).resolve().parents[1] / "docs" / "dnc.md"
#: A program as CAM writes it: its own % lines and CR LF ends (the control stores neither).
CAM = "%\r\nO1001 (PLATE)\r\nG21 G90 G17\r\nG00 X0 Y0 Z5.\r\nG01 Z-1. F300\r\nX20.\r\nM30\r\n%\r\n"


# -- 1. the request program against the control's digits ------------------------------------


@pytest.mark.parametrize(
    ("machine", "said"),
    [
        (
            "options = { o_digits = 4 }\n[machines.a.request]\nprogram = 123456\n",
            "[machines.a]: request.program = 123456 has 6 digits, but a's control takes 4 "
            "(options.o_digits = 4): it could never punch O123456",
        ),
        (
            "options = { o_digits = 3 }\n[machines.a.request]\nprogram = 9999\n",
            "request.program = 9999 has 4 digits, but a's control takes 3",
        ),
    ],
)
def test_a_request_program_the_control_cannot_number_is_refused_at_load(
    tmp_path: Path, machine: str, said: str
) -> None:
    (tmp_path / "dnc.toml").write_text(f'[machines.a]\nlink = "loop://"\n{machine}')
    with pytest.raises(UsageError) as caught:
        load_shop(tmp_path)
    assert said in str(caught.value)
    assert str(tmp_path / "dnc.toml") in str(caught.value)


@pytest.mark.parametrize(
    "machine",
    [
        "options = { o_digits = 4 }\nrequest = { program = 9999 }\n",
        "options = { o_digits = 8 }\nrequest = { program = 12345678 }\n",
        # not answered: its number does not matter
        "options = { o_digits = 4 }\nrequest = { program = 123456, enabled = false }\n",
    ],
)
def test_a_request_program_within_the_digits_is_taken(tmp_path: Path, machine: str) -> None:
    (tmp_path / "dnc.toml").write_text(f'[machines.a]\nlink = "loop://"\n{machine}')
    assert load_shop(tmp_path).machines["a"]


@pytest.mark.parametrize(
    ("request_table", "load", "drip"),
    [
        ('load = "DRIP"', "DRIP", "DRIP"),
        ('load = "drip"', "drip", "DRIP"),  # read in any case, as a request's words are
        ('load = "Send", drip = "SEND"', "Send", "SEND"),
    ],
)
def test_a_load_word_that_is_the_drip_word_is_refused_at_load(
    tmp_path: Path, request_table: str, load: str, drip: str
) -> None:
    """A request's words are read in any case: a load word equal to the drip word, in any
    case, would make every request a drip-feed (none a load): refused, naming both."""
    toml = tmp_path / "dnc.toml"
    toml.write_text(f'[machines.a]\nlink = "loop://"\nrequest = {{ {request_table} }}\n')
    with pytest.raises(UsageError) as caught:
        load_shop(tmp_path)
    said = str(caught.value)
    assert f"{toml}: [machines.a]: request.load = {load!r} and request.drip = {drip!r}" in said
    assert "are the same word" in said and "none for a load" in said, said


def test_load_and_drip_words_of_the_shop_s_own_are_read_in_any_case(tmp_path: Path) -> None:
    (tmp_path / "dnc.toml").write_text(
        '[machines.a]\nlink = "loop://"\nrequest = { load = "send", drip = "DNC" }\n'
    )
    convention = load_shop(tmp_path).machines["a"].request
    assert parse_request(9999, "(SEND O1234)", convention) == Request(1234, drip=False)
    assert parse_request(9999, "(dnc o1234)", convention) == Request(1234, drip=True)


@pytest.mark.parametrize(("digits", "program"), [(3, 999), (1, 9), (4, 9999), (8, 9999)])
def test_the_default_request_program_is_one_the_control_can_number(
    tmp_path: Path, digits: int, program: int
) -> None:
    """O9999, the highest 4-digit number, or the control's own highest with fewer digits."""
    toml = f'[machines.a]\nlink = "loop://"\noptions = {{ o_digits = {digits} }}\n'
    (tmp_path / "dnc.toml").write_text(toml)
    assert load_shop(tmp_path).machines["a"].request.program == program


async def test_dnc_serve_refuses_it_before_a_link_opens(shop: Shop) -> None:  # noqa: F811
    toml = shop.root / "dnc.toml"
    toml.write_text(toml.read_text() + "[machines.mill1.request]\nprogram = 123456\n")
    code, said = await run_here("dnc", "serve", "--dir", str(shop.root))
    assert code == 2, said
    assert "request.program = 123456 has 6 digits, but mill1's control takes 4" in said, said
    assert not (shop.root / "api.sock").exists()


# -- 2. program numbers out of the control's range -------------------------------------------


def test_the_g_code_check_says_the_control_s_range_in_plain_numbers() -> None:
    four = gcode.CheckOptions(o_digits=4)
    (zero,) = gcode.errors("O0000\nG00 X0\nM30\n", four)
    assert zero.message == "O0000: program number out of range 1 to 9999 (a 4-digit control)"
    (wide,) = gcode.errors("O12345\nG00 X0\nM30\n", four)
    assert wide.message.startswith("O12345: more than 4 digits")
    (tool,) = gcode.errors("O1\nT123456789\nM30\n", four)
    assert tool.message == "T123456789: tool number out of range 0 to 99999999"
    assert gcode.errors("O12345678\nG00 X0\nM30\n", gcode.CheckOptions(o_digits=8)) == []


async def test_a_number_out_of_range_is_said_so_before_any_file_is_looked_for(
    shop: Shop,  # noqa: F811
) -> None:
    root = str(shop.root)
    programs = ShopStore(shop.root).machine("mill1") / "programs"
    (programs / "O0000.nc").write_text("O0000\nG00 X0\nM30\n")
    # O0 is no program number (O1 to O9999): refused as the user wrote it, never made O0000
    for command, given in (("check", "O0"), ("send", "O0"), ("drip", "0")):
        code, said = await run_here("dnc", command, "mill1", given, "--dir", root)
        assert code == 2, (command, said)
        assert "O0 is out of range for mill1: its control takes programs O1 to O9999" in said
        assert "O0000" not in said and "no program" not in said, said
    # the file itself, checked: the G-code check says the same range
    code, said = await run_here("dnc", "check", "mill1", str(programs / "O0000.nc"), "--dir", root)
    assert code == 1, said
    assert "O0000: program number out of range 1 to 9999" in said and "e+" not in said, said
    for command in ("send", "drip", "check"):
        code, said = await run_here("dnc", command, "mill1", "O99999", "--dir", root)
        assert code == 2, (command, said)
        assert "O99999 is out of range for mill1" in said and "O1 to O9999" in said, said
        assert "no program" not in said and "a file named" not in said, said
    assert shop.controls["mill1"].chars_read == 0


# -- 3. a read-in's characters ---------------------------------------------------------------


async def test_a_read_in_s_counts_agree_and_say_what_they_count(shop: Shop) -> None:  # noqa: F811
    root = str(shop.root)
    (ShopStore(shop.root).machine("mill1") / "programs" / "O1001.nc").write_text(CAM)
    stored = len(unframe(CAM.encode()))
    code, said = await run_here("dnc", "check", "mill1", "O1001", "--dir", root)
    assert code == 0, said
    found = re.search(r"([\d,]+) characters of program \(what the control stores; its tape", said)
    assert found is not None and int(found.group(1)) == stored, said
    control = shop.controls["mill1"]
    sending = await cellctl("dnc", "send", "mill1", "O1001", "--dir", root)
    store = StateStore(shop.root)
    await until(lambda: store.load("mill1").get("state") == IsoCncState.READING, "the send", 30)
    control.read()  # the operator presses READ
    code, said = await finished(sending)
    assert code == 0, said
    assert control.memory[1001] == unframe(CAM.encode())
    message = re.search(
        rf"O1001\.nc: read in, {stored} characters of program in [\d.]+ s "
        r"\((\d+) tape characters on the line\)",
        said,
    )
    assert message is not None, said
    on_line = int(message.group(1))
    # the bar ends at its total, which is what went over the line
    bars = re.findall(r"(\d+)/(\d+) chars", said)
    assert bars and bars[-1] == (str(on_line), str(on_line)), said
    # the log says the same
    assert f"({on_line} tape characters on the line)" in "\n".join(
        ShopStore(shop.root).log_lines("mill1")
    )


# -- 4. waiting for the operator's read ------------------------------------------------------


async def test_a_request_waiting_for_cycle_start_says_what_to_do(served: Shop) -> None:  # noqa: F811
    root = str(served.root)
    control = served.controls["mill1"]
    control.memory[9999] = "O9999 (DRIP O1234)\n"
    control.set_mode(Mode.EDIT)
    control.punch(9999)
    waiting = "drip-feeding O1234.nc: waiting for read: press CYCLE START on the control"
    await wait_state(served, "mill1", waiting)
    code, said = await finished(await cellctl("dnc", "status", "--dir", root))
    assert code == 0, said
    assert f"mill1: busy: {waiting}, in RMT (DNC) mode | 0/" in said, said
    code, said = await finished(await cellctl("dnc", "send", "mill1", "O1234", "--dir", root))
    assert code == 6, said
    assert f"mill1 is busy: {waiting}" in said, said
    # docs/dnc.md gives the same words
    docs = " ".join(DOCS.read_text().split())
    assert (
        "drip-feeding O1234.nc: waiting for read: press CYCLE START on the control, in RMT" in docs
    )
    code, said = await finished(await cellctl("dnc", "stop", "mill1", "--dir", root))
    assert code == 0 and "cancelled before the control began its read" in said, said
    assert control.chars_read == 0


# -- 5. a zero feed --------------------------------------------------------------------------


def test_a_zero_feed_is_said_as_such_and_where() -> None:
    (here,) = gcode.errors("O1\nG21\nG01 X10. F0\nM30\n")
    assert (
        here.format("p.nc")
        == "p.nc:3:10: G01 move with a feed of zero (F0): the axes would not move"
    )
    (earlier,) = gcode.errors("O1\nF0\nG00 X0\nG01 X10.\nM30\n")
    assert earlier.line == 4
    assert "feed of zero (F0 at line 2, column 1, is the feed in force)" in earlier.message
    (none,) = gcode.errors("O1\nG01 X10.\nM30\n")
    assert none.message == "G01 move with no feed: no F before it"


# -- 6. a machine whose link is down ---------------------------------------------------------


async def test_a_machine_whose_link_is_down_is_said_so(tmp_path: Path) -> None:
    held = refusing_port()  # nothing answers there
    port = held.getsockname()[1]
    root = tmp_path / "shop"
    root.mkdir()
    (root / "dnc.toml").write_text(f'[machines.m1]\nlink = "socket://127.0.0.1:{port}"\n')
    (ShopStore(root).machine("m1") / "programs" / "O1001.nc").write_text(CAM)
    try:
        # no server: the one-shot command tries once and says so, no promise of a retry
        code, said = await finished(await cellctl("dnc", "send", "m1", "O1001", "--dir", str(root)))
        assert code == 3, said
        assert "m1: offline: " in said and "tried again" not in said, said
        assert "m1: read-in of O1001" not in said, said  # no prompt before the refusal
        server = await cellctl("dnc", "serve", "--dir", str(root))
        try:
            await until(lambda: (root / "api.sock").exists(), "dnc serve's API", 30)
            code, said = await finished(
                await cellctl("dnc", "receive", "m1", "--timeout", "2", "--dir", str(root))
            )
            assert code == 3, said
            assert "its link is down: nothing can be punched to the server until it is back" in said
            assert "press PUNCH" not in said and "nothing punched" not in said, said
        finally:
            server.terminate()
            await finished(server, 20)
    finally:
        held.close()


async def test_a_receive_waiting_is_told_when_the_link_goes_down(served: Shop) -> None:  # noqa: F811
    receiver = await cellctl(
        "dnc", "receive", "mill2", "--timeout", "60", "--dir", str(served.root)
    )
    await wait_state(served, "mill2", "waiting for punch")
    await served.servers[1].close()  # the device server goes away
    code, said = await finished(receiver, 30)
    assert code == 3, said
    assert "mill2: offline: " in said and "its link is down" in said, said
