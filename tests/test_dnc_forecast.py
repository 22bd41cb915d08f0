"""The drip-feed forecast (``cellctl dnc check``): the driver's model of the control's buffer
played at a line rate, against what the emulated control records when the driver really
drip-feeds the same tape to it (over mem:// on virtual time: the line's pace and the motion
as in life, in a moment); and the command as a shop's user runs it."""

from __future__ import annotations

import asyncio
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.clock import current_clock, run_virtual
from cellctl.emulators.memserve import serve_mem
from cellctl.errors import UsageError
from cellctl.kinds.iso_cnc.buffer import DripForecast, forecast_drip, tape_blocks
from cellctl.kinds.iso_cnc.driver import IsoCncDriver, IsoCncOptions
from cellctl.kinds.iso_cnc.emulator import EmulatorOptions, IsoCncEmulator, Mode
from cellctl.kinds.iso_cnc.options import prepare
from cellctl.link import LineSettings
from cellctl.ui.cli import main
from tests.test_iso_cnc_link import surfacing

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell-tending" / "programs"


def forecast(data: bytes, line: LineSettings, options: IsoCncOptions) -> DripForecast:
    framed = prepare(data, options, "O1234")
    blocks = tape_blocks(framed, options.motion(), options.motion_scale)
    return forecast_drip(framed, blocks, line.char_time, options.sender(line.char_time))


def drip(data: bytes, line: LineSettings, options: IsoCncOptions) -> tuple[float, float, int]:
    """The driver's drip-feed into the emulated control: (seconds from the control's first
    DC1 to its last block's end, seconds its axes waited for data, blocks they waited at)."""
    out: list[tuple[float, float, int]] = []

    async def session() -> None:
        control = IsoCncEmulator(EmulatorOptions(auto_operator=True))
        control.mode = Mode.RMT
        server = await serve_mem(control, line, name="mill1")
        driver = await IsoCncDriver.connect(server.url, settings=line, options=options)
        try:
            clock = current_clock()
            began = clock.monotonic()
            await driver.drip_feed(data, timeout=3600)
            run = control.runs[-1]
            assert run.done and control.alarms == []
            out.append((clock.monotonic() - began, run.stall_s, len(run.stalls)))
        finally:
            await driver.close()
            await server.close()

    run_virtual(session())
    return out[0]


@pytest.mark.parametrize("baud", [4800, 9600, 19200])
def test_the_forecast_is_what_the_control_records(baud: int) -> None:
    line = LineSettings(baud, 7, "E", 2)
    options = IsoCncOptions()
    data = surfacing(30)
    told = forecast(data, line, options)
    elapsed, stall_s, stalls = drip(data, line, options)
    # Within 5 % (and 50 ms: the control's own timing of its first block and DC1).
    assert abs(told.stall_s - stall_s) <= 0.05 * stall_s + 0.05, (told, stall_s)
    assert abs(told.stalls - stalls) <= max(3, 0.05 * stalls), (told, stalls)
    assert abs(told.end_s - elapsed) <= 0.01 * elapsed + 0.05, (told, elapsed)
    assert told.run_s <= told.end_s
    if told.stalls:
        assert told.longest_block.startswith("G1 ")


def test_a_block_longer_than_the_buffers_room_is_forecast_as_the_driver_sends_it() -> None:
    # 230 characters: within a block's limit (256), beyond what the host keeps in the
    # control's buffer (256 - 10 - 24): the model has no block end to wait for, and the
    # driver writes on with the control's DC3 as its guard.
    long = "G01 X1.000 Y1.000 F300 (" + "A" * 205 + ")"
    data = f"%\nO1235\nG21 G90\n{long}\nG01 X2 Y2\nM30\n%\n".encode()
    line = LineSettings(9600, 7, "E", 2)
    told = forecast(data, line, IsoCncOptions())
    elapsed, _, _ = drip(data, line, IsoCncOptions())
    assert told.chars > len(long) and told.stalls == 0
    assert abs(told.end_s - elapsed) <= 0.01 * elapsed + 0.05, (told, elapsed)


@pytest.fixture
def shop(tmp_path: Path) -> Path:
    (tmp_path / "dnc.toml").write_text(
        '[machines.mill1]\nlink = "socket://127.0.0.1:9"\nline = "9600,7E2"\n'
    )
    programs = tmp_path / "mill1" / "programs"
    programs.mkdir(parents=True)
    (programs / "O1234 surface.nc").write_bytes(surfacing(30))
    shutil.copy(EXAMPLE / "O1001.nc", programs / "O1001.nc")
    return tmp_path


def dnc(shop: Path, *args: str) -> tuple[int, str]:
    result = CliRunner().invoke(main, ["dnc", *args, "--dir", str(shop)])
    return result.exit_code, result.output


def test_dnc_check_forecasts_the_wait_and_the_rate_that_avoids_it(shop: Path) -> None:
    code, said = dnc(shop, "check", "mill1", "O1234")
    assert code == 0, said
    told = forecast(surfacing(30), LineSettings(9600, 7, "E", 2), IsoCncOptions())
    assert "O1234 (O1234 surface.nc) for mill1 at 9600,7E2: 188 blocks that take time" in said
    assert f"the axes wait {told.stall_s:.1f} s for data at {told.stalls:,} blocks" in said
    assert "no wait from 19200 baud" in said
    code, said = dnc(shop, "check", "mill1", "O1001")
    assert code == 0, said
    assert "the axes never wait for data" in said and "no wait from" not in said


def test_dnc_check_refuses_as_send_would(shop: Path) -> None:
    bad = shop / "nofeed.nc"
    bad.write_text("%\nO1001\nG21 G90\nG00 X0 Y0\nG01 X10 Y10\nM30\n%\n")
    code, said = dnc(shop, "check", "mill1", str(bad))
    assert code == 1
    assert (
        f"{bad}:5: G01 move with no feed" in said and "cellctl refuses to send it to mill1" in said
    )
    renamed = shop / "mill1" / "programs" / "O1002.nc"
    shutil.copy(EXAMPLE / "O1001.nc", renamed)
    code, said = dnc(shop, "check", "mill1", "O1002")  # a problem like the others: exit 1
    assert code == 1 and "its name says O1002 but its text is O1001" in said, said
    assert "1 problem(s): cellctl refuses to send it to mill1" in said
    latin = shop / "latin.nc"
    latin.write_bytes(b"%\nO1003\nG21 (D\xc9BUT)\nM30\n%\n")
    code, said = dnc(shop, "check", "mill1", str(latin))
    assert code == 2 and f"{latin}: not ISO code: byte 15 is 0xC9 (a program is 7-bit" in said
    code, said = dnc(shop, "check", "millx", "O1001")
    assert code == 2 and "unknown machine 'millx'" in said


def test_a_long_programs_check_leaves_the_loop_free() -> None:
    """A program of 1.4 MB takes seconds of G-code check: it is checked off the event loop, so
    a server's other machines are answered meanwhile (here: another task runs, turn after
    turn, before the check refuses the program's last block). The control hears nothing."""
    rows = ["O1234", "G21 G90 G0 X0 Y0", *(f"G1 X{i % 100}.0 F500" for i in range(100_000))]
    data = ("\n".join([*rows, "G1 X#", "M30"]) + "\n").encode()
    line = LineSettings(9600, 7, "E", 2)
    order: list[str] = []

    async def session() -> None:
        control = IsoCncEmulator(EmulatorOptions(auto_operator=True))
        server = await serve_mem(control, line, name="mill1")
        driver = await IsoCncDriver.connect(server.url, settings=line, options=IsoCncOptions())

        async def other_machine() -> None:
            for _ in range(20):
                await asyncio.sleep(0)
            order.append("another machine answered")

        async def send() -> None:
            with pytest.raises(UsageError, match=r":100003:4: X without a number"):
                await driver.read_in(data, timeout=60)
            order.append("refused")

        try:
            await asyncio.gather(send(), other_machine())
            assert driver.link.bytes_sent == 0
        finally:
            await driver.close()
            await server.close()

    run_virtual(session())
    assert order == ["another machine answered", "refused"]
