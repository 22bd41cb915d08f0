"""A mill whose line is gone says so: never the readiness it last saw.

On a bench: the mill behind a device server (RFC 2217, CTS on the line) or on a pty with
in-band readiness, its cable pulled (the emulator's server closed). The cell's monitor reads
an idle mill's status; a status that still said READY from the level last seen returned the
mill's link alarm to normal, the reopen failed and raised it again, several times a second
for as long as the cable was out.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest

from cellctl.drivers.state import StateStore
from cellctl.emulators.serve import serve
from cellctl.errors import LinkClosed
from cellctl.kinds.dyna2400.driver import Dyna2400Mill, MillConfig
from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator, OperatorDelays
from cellctl.link import LineSettings, Link, open_link

FAST_LINE = LineSettings(115200, 8, "N", 1)
#: Seconds the host may take to hear that the far end closed.
CLOSED_S = 10.0


async def _closed(link: Link) -> None:
    """Read ``link`` until it says the far end closed (LinkTimeout if nothing comes within
    CLOSED_S)."""
    with contextlib.suppress(LinkClosed):
        while True:
            await link.read(timeout=CLOSED_S)
    assert link.closed


def _emulator(readiness: str) -> Dyna2400Emulator:
    delays = OperatorDelays(power_on=1.0, keys=1.0, setup=100.0)
    return Dyna2400Emulator(time_scale=1000.0, delays=delays, readiness=readiness, min_busy_s=0.05)


@pytest.mark.parametrize(
    ("listen", "readiness"), [("rfc2217://127.0.0.1:0", "modem"), ("pty", "inband")]
)
async def test_a_mill_whose_cable_is_pulled_is_not_ready_but_closed(
    listen: str, readiness: str, tmp_path: Path
) -> None:
    emulator = _emulator(readiness)
    where = f"pty:{tmp_path}/mill" if listen == "pty" else listen
    server = await serve(emulator, where, FAST_LINE, pacing=False)
    emulator.start()
    mill = await Dyna2400Mill.connect(
        server.url,
        name="cnc1",
        settings=FAST_LINE,
        store=StateStore(tmp_path),
        config=MillConfig(readiness=readiness, pace_writes=False),
    )
    try:
        await mill._ready.wait(True, CLOSED_S)  # the operator powered it on
        assert (await mill.status()).ready
        await server.close()  # the cable pulled
        await _closed(mill.link)
        with pytest.raises(LinkClosed):
            await mill.status()
    finally:
        await mill.close()


async def test_rfc2217_cts_of_a_closed_connection_is_link_closed() -> None:
    server = await serve(_emulator("modem"), "rfc2217://127.0.0.1:0", FAST_LINE, pacing=False)
    link = await open_link(server.url, FAST_LINE)
    try:
        await link.cts()  # the server has told its modem state
        await server.close()
        await _closed(link)
        with pytest.raises(LinkClosed):
            await link.cts()
    finally:
        await link.close()
