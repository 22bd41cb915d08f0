"""The iso-cnc driver against the emulated control through real links: a pty, loopback TCP,
ser2net in RFC 2217 mode, the emulator's own RFC 2217 (CS carried). Time runs SCALE times
faster: the line's baud rate, the control's motion and the adapter's latency together."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from cellctl.emulators.serve import Server, serve
from cellctl.errors import LinkTimeout, UsageError
from cellctl.kinds.iso_cnc import gcode, motion, tape
from cellctl.kinds.iso_cnc.driver import (
    ControlAlarm,
    IsoCncDriver,
    IsoCncOptions,
    TransferProgress,
)
from cellctl.kinds.iso_cnc.emulator import Activity, EmulatorOptions, IsoCncEmulator, Mode
from cellctl.link import LineSettings, TrafficLog
from cellctl.service.functions import function

from .conftest import Ser2net, emulator_process, until

SCALE = 2.0
LINE = LineSettings(int(9600 * SCALE), 7, "E", 2)
DEADLINE = 60.0
#: Where the line's timing decides (the control's buffer against the host's model), the
#: control is served on loopback TCP, not a pty: the kernel moves a pty's bytes in a worker
#: thread that waits for a CPU, so on a loaded box a pty holds the host's characters 0.1 to
#: 2.5 s and then hands them over at once, which no serial line does (a device server that
#: holds them is declared with ``link_lag_s``). Loopback TCP hands them across within the
#: write (under 5 ms at load 10, the same box).
TIMED = "socket://127.0.0.1:0"


def surfacing(rows: int, *, slow_every: int = 10) -> bytes:
    """A small surfacing program as CAM writes it: 1 mm segments at F3000 (faster than the
    line feeds them), and every ``slow_every`` rows a slow plunge (slower: the buffer fills)."""
    lines = ["%", "O1234 (SURFACE)", "G21 G90 G17", "G0 X0 Y0 Z5", "G1 Z0 F3000"]
    for row in range(rows):
        y = row * 0.5
        for i in range(6):
            lines.append(f"G1 X{(i if row % 2 == 0 else 5 - i):.3f} Y{y:.3f} Z{-0.01 * i:.3f}")
        if row % slow_every == slow_every - 1:
            lines.append("G1 Z-1 F60")
            lines.append("G1 Z0 F3000")
    lines += ["G0 Z5", "M30", "%"]
    return ("\n".join(lines) + "\n").encode()


@dataclass
class Cnc:
    control: IsoCncEmulator
    server: Server
    driver: IsoCncDriver
    trace: TrafficLog


async def connect(
    tmp_path: Path,
    control: IsoCncEmulator,
    *,
    listen: str = "pty",
    options: IsoCncOptions | None = None,
    via_ser2net: bool = False,
) -> tuple[Server, IsoCncDriver, TrafficLog, Ser2net | None]:
    server = await serve(control, listen, LINE)
    proxy = None
    url = server.url
    if via_ser2net:
        proxy = Ser2net(server.url, f"{LINE.baudrate}e72", tmp_path)
        await proxy.wait_listening()
        url = proxy.url
    trace = TrafficLog(tmp_path / "traffic.log")
    chosen = options or IsoCncOptions(motion_scale=SCALE, dc1_timeout=10, end_extra=10)
    driver = await IsoCncDriver.connect(url, settings=LINE, options=chosen, trace=trace)
    return server, driver, trace, proxy


@pytest.fixture
async def cnc(tmp_path: Path) -> AsyncIterator[Cnc]:
    control = IsoCncEmulator(EmulatorOptions(auto_operator=True), time_scale=SCALE)
    server, driver, trace, _ = await connect(tmp_path, control)
    yield Cnc(control, server, driver, trace)
    await driver.close()
    await server.close()


def latency_control(latency_ms: float, mode: Mode, **more: object) -> IsoCncEmulator:
    """A control whose DC1/DC3 reach the host ``latency_ms`` (control time) late."""
    options = EmulatorOptions(adapter_latency_ms=latency_ms, auto_operator=True, **more)  # type: ignore[arg-type]
    control = IsoCncEmulator(options, time_scale=SCALE)
    control.mode = mode
    return control


# A real-time margin (the host's buffer model against DC3s 16 ms late): on a box loaded by
# the other tests, a late loop hands the control bursts no line would; measured alone.
@pytest.mark.alone
@pytest.mark.parametrize("latency_ms", [0, 2, 8, 16])
async def test_read_in_and_drip_feed_never_overflow_at_any_adapter_latency(
    tmp_path: Path, latency_ms: float
) -> None:
    data = surfacing(12)
    control = latency_control(latency_ms, Mode.EDIT)
    server, driver, _, _ = await connect(tmp_path, control, listen=TIMED)
    try:
        seen: list[TransferProgress] = []
        report = await driver.read_in(data, progress=seen.append, timeout=DEADLINE)
        assert control.memory[1234] == tape.unframe(data)  # byte for byte after % framing
        framed = tape.frame(data.decode(), leader=20, trailer=20)
        # everything up to the closing %; the trailer's NULs stop at the control's DC3
        assert report.chars_total == len(framed)
        assert framed.rfind(b"%") < report.chars_sent <= report.chars_total
        assert seen[0].phase == "waiting" and seen[-1].phase == "done"

        control.set_mode(Mode.RMT)
        report = await driver.drip_feed(data, timeout=DEADLINE)
        run = control.runs[-1]
        assert run.done and run.blocks == data.count(b"\n") - 2  # every block but the %s
        assert control.alarms == []
        assert control.overflow_chars <= control.tolerance
        assert framed.rfind(b"%") < report.chars_sent <= report.chars_total
        # the slow blocks filled the buffer: the host held back by its model, not by luck
        assert control.peak_buffer > control.options.buffer_size // 2
    finally:
        await driver.close()
        await server.close()


async def test_a_host_that_only_reacts_to_dc3_overflows_at_16_ms(tmp_path: Path) -> None:
    """The failure the buffer model prevents: told the control's buffer is 4096 (so its model
    never stops it), the driver only has the DC3 to go by, which comes 14 characters late."""
    control = latency_control(16, Mode.RMT)
    blind = IsoCncOptions(
        motion_scale=SCALE, buffer_size=4096, dc1_timeout=10, end_extra=10, burst=16
    )
    server, driver, _, _ = await connect(tmp_path, control, listen=TIMED, options=blind)
    try:
        with pytest.raises(ControlAlarm) as caught:
            await driver.drip_feed(surfacing(12), timeout=DEADLINE)
        assert caught.value.code == 87 and "BUFFER OVERFLOW" in str(caught.value)
        assert control.alarms[-1].code == 87 and control.activity == Activity.ALARM
        assert driver.host_status().shown == "alarm 087 BUFFER OVERFLOW"
    finally:
        await driver.close()
        await server.close()


#: A device server that holds each piece of the host's data 0 to 400 ms (control time).
LAG_MS = 400.0


async def test_a_line_that_holds_characters_a_varying_time_is_safe_with_its_lag_allowed(
    tmp_path: Path,
) -> None:
    """Characters held a varying time on their way start their blocks late by a varying
    amount (the scaled bench's own process does this to its control): a host whose model
    allows for the lag (``link_lag_s``) stays under the high-water mark even when its DC3
    would come 14 characters late. Without the allowance the same run overflows (087) in
    most runs: the model counts blocks out before they have started."""
    control = latency_control(16, Mode.RMT, line_lag_ms=LAG_MS)
    options = IsoCncOptions(
        motion_scale=SCALE, dc1_timeout=10, end_extra=10, link_lag_s=LAG_MS / 1000 / SCALE
    )
    server, driver, _, _ = await connect(tmp_path, control, listen=TIMED, options=options)
    data = surfacing(12, slow_every=2)
    try:
        await driver.drip_feed(data, timeout=DEADLINE)
        run = control.runs[-1]
        assert run.done and run.blocks == data.count(b"\n") - 2
        assert control.alarms == [] and control.overflow_chars <= control.tolerance
        # the slow blocks filled the buffer: the host held back by its model, not by luck
        assert control.peak_buffer > control.options.buffer_size // 2
    finally:
        await driver.close()
        await server.close()


async def test_through_ser2net_rfc2217_the_program_arrives_whole(
    tmp_path: Path, ser2net_available: None
) -> None:
    data = surfacing(6)
    control = latency_control(2, Mode.EDIT)
    server, driver, _, proxy = await connect(tmp_path, control, via_ser2net=True)
    assert proxy is not None
    try:
        # ser2net opens the device when the driver connects: READ is pressed after that
        control.set_mode(Mode.EDIT)
        await driver.read_in(data, timeout=10)
        assert control.memory[1234] == tape.unframe(data)
        control.set_mode(Mode.RMT)
        await driver.drip_feed(data, timeout=DEADLINE)
        assert control.runs[-1].done and control.alarms == []
    finally:
        await driver.close()
        proxy.stop()
        await server.close()


async def test_cs_flow_over_rfc2217_with_a_two_character_tolerance(tmp_path: Path) -> None:
    """A CS-only control (tolerance 2) drops RTS when full; the host obeys CTS."""
    control = latency_control(0, Mode.RMT, cs_flow=True, tolerance=2)
    options = IsoCncOptions(
        motion_scale=SCALE, cs_flow=True, dc3_tolerance=2, dc1_timeout=10, end_extra=10
    )
    server, driver, _, _ = await connect(
        tmp_path, control, listen="rfc2217://127.0.0.1:0", options=options
    )
    try:
        await driver.drip_feed(surfacing(6), timeout=DEADLINE)
        assert control.runs[-1].done and control.alarms == []
        assert control.overflow_chars <= 2
    finally:
        await driver.close()
        await server.close()


async def test_parity_noise_is_alarm_085_in_the_spec_s_words(cnc: Cnc) -> None:
    cnc.control.set_fault("parity-noise", "1")
    with pytest.raises(ControlAlarm) as caught:
        await cnc.driver.read_in(surfacing(2), timeout=DEADLINE)
    assert caught.value.code == 85 and "COMMUNICATION ERROR" in str(caught.value)
    assert cnc.control.alarms[-1].code == 85


async def test_dr_off_is_alarm_086(cnc: Cnc) -> None:
    cnc.control.reset()
    cnc.control.set_fault("dr-off")
    cnc.control.set_mode(Mode.EDIT)  # READ pressed again: DR is off
    with pytest.raises(ControlAlarm) as caught:
        await cnc.driver.read_in(surfacing(2), timeout=DEADLINE)
    assert caught.value.code == 86 and "DR OFF" in str(caught.value)


async def test_a_control_that_never_sends_dc1_times_out_in_words(tmp_path: Path) -> None:
    control = IsoCncEmulator(EmulatorOptions(never_dc1=True, auto_operator=True), time_scale=SCALE)
    options = IsoCncOptions(motion_scale=SCALE, dc1_timeout=0.5)
    server, driver, _, _ = await connect(tmp_path, control, options=options)
    try:
        with pytest.raises(LinkTimeout, match="no DC1 \\(tape reader start\\)"):
            await driver.read_in(surfacing(2))
        assert driver.link.bytes_sent == 0  # nothing before DC1
    finally:
        await driver.close()
        await server.close()


@pytest.mark.parametrize(
    ("program", "words"),
    [
        (b"%\nO1234\nG1 X10\nM30\n%\n", "no F before it"),
        (b"%\nO1234\nG0 G1 X1 F100\nM30\n%\n", "G0 and G1 in one block"),
        (b"%\nO1234\nG90 G0 X0 Y0\nG2 X10 Y0 I3 J0 F100\nM30\n%\n", "radius"),
        (b"%\nG0 X1\nM30\n%\n", "no O-number"),
        (b"%\nO1234\nG0 X1 \xff\nM30\n%\n", "not ISO code"),
    ],
)
async def test_a_bad_program_is_refused_before_a_byte_goes_out(
    cnc: Cnc, program: bytes, words: str
) -> None:
    with pytest.raises(UsageError, match=words):
        await cnc.driver.read_in(program)
    with pytest.raises(UsageError):
        await cnc.driver.run(Path("/nonexistent/O1234.nc"))
    assert cnc.driver.link.bytes_sent == 0
    assert cnc.control.chars_read == 0


async def test_punch_receive_gets_the_program_from_dc2_to_dc4(cnc: Cnc) -> None:
    text = "O0042 (BACKUP)\nG21 G90\nG0 X1 Y2\nM30\n"
    # the operator leaves READ and presses PUNCH instead
    cnc.control.options = cnc.control.options.model_copy(update={"auto_operator": False})
    cnc.control.set_mode(Mode.EDIT)
    cnc.control.memory[42] = text
    cnc.control.punch(42)
    punched = await cnc.driver.receive(timeout=DEADLINE)
    assert tape.unframe(punched) == text
    assert tape.split_programs(tape.unframe(punched))[0].number == 42
    await until(lambda: cnc.control.activity == Activity.IDLE, "the punch to end")


async def test_cellctl_emulate_iso_cnc_serves_a_control_in_its_own_process(
    tmp_path: Path,
) -> None:
    args = ["iso-cnc", "--mode", "EDIT", "--auto-operator", "--time-scale", str(SCALE)]
    with emulator_process(*args, "--line", str(LINE), "--fault", "adapter-latency=16") as url:
        options = IsoCncOptions(motion_scale=SCALE, dc1_timeout=10, end_extra=10)
        driver = await IsoCncDriver.connect(url, settings=LINE, options=options)
        try:
            report = await driver.read_in(surfacing(4), timeout=DEADLINE)
            assert report.chars_sent > 0  # it asked with DC1 and ended the read with DC3
        finally:
            await driver.close()


async def test_a_punch_pauses_on_the_host_s_dc3_and_goes_on_at_dc1(cnc: Cnc) -> None:
    text = "".join(["O0043 (LONG)\n", *(f"G1 X{i}.5 Y{i} F500\n" for i in range(200)), "M30\n"])
    cnc.control.options = cnc.control.options.model_copy(update={"auto_operator": False})
    cnc.control.set_mode(Mode.EDIT)
    cnc.control.memory[43] = text
    cnc.control.punch(43)
    receiving = asyncio.ensure_future(cnc.driver.receive(timeout=DEADLINE))
    await until(lambda: cnc.control.punched > 100, "the punch to start")
    await cnc.driver.pause()
    await until(lambda: cnc.control.punch_held or receiving.done(), "the punch to stop")
    assert not receiving.done() and cnc.control.punch_overrun <= 10  # the spec's 10
    held = cnc.control.punched
    await cnc.driver.resume()
    punched = await receiving
    assert cnc.control.punched > held and tape.unframe(punched) == text


async def test_a_program_read_into_memory_runs_from_memory_in_its_motion_time(cnc: Cnc) -> None:
    data = surfacing(2)
    await cnc.driver.read_in(data, timeout=DEADLINE)
    cnc.control.set_mode(Mode.MEM)
    cnc.control.selected = 1234
    cnc.control.cycle_start()
    await until(lambda: cnc.control.runs and cnc.control.runs[-1].done, "the memory run")
    run = cnc.control.runs[-1]
    blocks = gcode.blocks(tape.unframe(data))
    assert run.number == 1234 and run.blocks == len(blocks)
    assert run.machine_s == pytest.approx(motion.program_seconds(blocks))


async def test_the_menu_s_status_is_the_host_s_view_and_sends_nothing(cnc: Cnc) -> None:
    status = function("mill", "status", "iso-cnc")
    params = status.check({})
    before = cnc.trace.sent()
    idle = await status.run(cnc.driver, params)
    assert (idle["message"], idle["state_text"], idle["alarm"]) == ("idle", "idle", None)
    assert cnc.trace.sent() == before  # a control on RS-232 answers no status request
    cnc.control.set_mode(Mode.RMT)
    feed = asyncio.ensure_future(cnc.driver.drip_feed(surfacing(12), timeout=DEADLINE))
    seen: list[dict[str, object]] = []

    async def feeding() -> bool:
        seen.append(await status.run(cnc.driver, params))
        return seen[-1]["state_text"] == "drip-feeding" and seen[-1]["chars_sent"] != 0

    try:
        await until(feeding, "the drip-feed under way")
    finally:
        await feed
    during = seen[-1]
    assert str(during["message"]).startswith(f"drip-feeding {during['chars_sent']}/")
    assert f"/{during['chars_total']} chars" in str(during["message"])
    assert (await status.run(cnc.driver, params))["message"] == "idle"
