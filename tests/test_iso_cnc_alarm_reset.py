"""An iso-cnc control's alarm and its RESET, as the host and the operator meet them: the
control keeps an alarm once its cause is gone (DR back on) until its operator resets it; the
reset reaches the host as SYN (spec, "Alarms the host must understand"), so a host holding the
alarm takes work again; an alarm report that comes while an RFC 2217 link opens is the host's
from its first look; and the emulated cell's panel (`clear vf2`) says what the control shows
after its RESET, never a reset that did not clear it. Real sockets, the emulators' own panels."""

from __future__ import annotations

import tomllib
from collections.abc import Awaitable, Callable
from pathlib import Path

from cellctl.emulators.cell import EmulatedCell
from cellctl.emulators.cellpanel import hand_command
from cellctl.emulators.serve import serve
from cellctl.kinds.iso_cnc.driver import IsoCncDriver
from cellctl.kinds.iso_cnc.emulator import EmulatorOptions, IsoCncEmulator, Mode
from cellctl.kinds.iso_cnc.status import IsoCncState, IsoCncStatus
from cellctl.kinds.iso_cnc.tape import SYN
from cellctl.link import LineSettings, open_link
from tests.conftest import until

LINE = LineSettings.parse("9600,7E2")
TENDING = Path(__file__).resolve().parent.parent / "examples" / "cell-tending"
PROGRAM = b"O0042 (BRACKET)\nG21 G90\nG0 X1. Y2.\nG1 X5. F3000\nM30\n"


async def test_the_host_knows_an_alarm_from_the_links_opening_and_its_reset() -> None:
    """DR off as the host connects: the control's CYCLE START (its operator's, as the host
    came) raises 086 and reports it while the RFC 2217 link is still being negotiated. The
    host holds it from the start, before it sends a byte; the operator's RESET once DR is
    back clears it on both sides, and a drip-feed then runs."""
    control = IsoCncEmulator(EmulatorOptions(auto_operator=True, dr_off=True), time_scale=50)
    control.mode = Mode.RMT
    # Unpaced: its report crosses at once, before the link's negotiation is answered.
    server = await serve(control, "rfc2217://127.0.0.1:0", LINE, pacing=False)
    cnc = await IsoCncDriver.connect(server.url, settings=LINE)
    try:
        assert cnc.host_status().shown == "alarm 086 DR OFF"  # no byte asked, no wait
        assert (await cnc.status()).kind_condition.value == "alarm"
        # DR back: the control keeps its alarm (as a Fanuc does) until someone resets it.
        control.clear_fault("dr-off")
        assert control.display == "ALARM 086 DR OFF"
        assert (await cnc.status()).shown == "alarm 086 DR OFF"
        await control.operator_after("dr-off")  # RESET at the control
        assert not control.alarmed
        status = await until(_idle(cnc), "the host to take the control's reset (SYN)", 30)
        assert status.state == IsoCncState.IDLE and cnc.alarm is None
        await cnc.drip_feed(PROGRAM, timeout=30)  # the control asks, runs it to its end
        assert control.runs[-1].done and control.runs[-1].blocks == 5
        assert cnc.host_status().state == IsoCncState.IDLE and not control.alarmed
    finally:
        await cnc.close()
        await server.close()
        await control.stop()


def _idle(cnc: IsoCncDriver) -> Callable[[], Awaitable[IsoCncStatus | None]]:
    """A look at the host's status: the status once it is idle, else None."""

    async def look() -> IsoCncStatus | None:
        status = await cnc.status()
        return status if status.state == IsoCncState.IDLE else None

    return look


async def test_clear_at_the_panel_says_what_the_control_still_shows(tmp_path: Path) -> None:
    """`clear vf2` at the emulated cell's panel: RESET with DR still off clears nothing that
    lasts (the next read raises 086 again), and it says so; with DR back it clears, says what
    the control shows now, and the host hears SYN. A robot whose kind keeps nothing to reset
    at the machine is told so, not "reset"."""
    cell = EmulatedCell(time_scale=200.0, template=TENDING)
    toml = await cell.start(tmp_path / "cell")  # the cell.toml it wrote
    url = tomllib.loads(toml.read_text())["machines"]["vf2"]["link"]
    cell.set_fault("vf2", "dr-off")
    link = await open_link(url, LINE)
    try:
        # The host came: the control's operator pressed CYCLE START, DR is off: 086.
        shown = await until(_shown(cell, "vf2: ALARM 086 DR OFF"), "the alarm on vf2's screen")
        assert "vf2: ALARM 086 DR OFF" in shown
        said = await hand_command(cell, "clear vf2")
        assert said == (
            "vf2: not cleared: it still shows ALARM 086 DR OFF (its cause is still there: "
            "see to it, then clear again)"
        ), said
        cell.machine("vf2").clear_fault("dr-off")  # the cable back in
        assert "vf2: ALARM 086 DR OFF" in await hand_command(cell, "show")
        link.reset_input()
        said = await hand_command(cell, "clear vf2")
        assert said == "vf2: ALARM 086 DR OFF cleared: RMT reading", said
        heard = await link.read_until(SYN, timeout=10)
        assert heard.endswith(SYN)
        assert await hand_command(cell, "clear vf2") == "vf2: nothing to clear (RMT reading)"
        said = await hand_command(cell, "clear robot")
        assert said == "robot: nothing to reset at the machine (its kind keeps no error condition)"
    finally:
        await link.close()
        await cell.close()


def _shown(cell: EmulatedCell, words: str) -> Callable[[], Awaitable[str | None]]:
    """A look at the panel's `show`: what it shows once it has ``words``, else None."""

    async def look() -> str | None:
        shown = await hand_command(cell, "show")
        return shown if words in shown else None

    return look
