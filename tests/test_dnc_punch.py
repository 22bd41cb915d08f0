"""A punch as a shop meets it at the server: one that stops half-way (the operator turns
the mode switch, a cable is pulled: no DC4 ever comes, the link stays up), how it shows
while it comes, and ``dnc serve`` stopped while a ``dnc receive`` waits for one. Real
processes (``cellctl dnc ...``) against emulated controls on a pty and TCP."""

from __future__ import annotations

import re
import signal
from pathlib import Path

from cellctl.kinds.iso_cnc.dnc.line import PUNCH_IDLE_S
from cellctl.kinds.iso_cnc.dnc.store import ShopStore
from cellctl.kinds.iso_cnc.emulator import Mode
from tests.conftest import until
from tests.test_dnc_cli import (  # noqa: F401  (shop and served are fixtures)
    Shop,
    cellctl,
    finished,
    served,
    shop,
    wait_state,
)
from tests.test_dnc_server import surfacing

#: Moves of the program punched: about 50 s of line time at 9600 baud, so the punch is
#: still coming when the test looks at it or stops it.
MOVES = 4000


async def punch_under_way(where: Shop, name: str) -> dict[str, object]:
    """The machine's progress once its punch has brought some characters."""

    async def coming() -> dict[str, object] | None:
        m = (await where.status())["machines"][name]
        p = m["progress"] or {}
        return p if m["state"] == "punching" and int(p.get("done", 0)) > 0 else None

    found: dict[str, object] = await until(coming, f"{name}'s punch under way", 30)
    return found


async def status_row(root: Path, name: str) -> str:
    """Machine ``name``'s line of ``cellctl dnc status`` (exit 0)."""
    code, said = await finished(await cellctl("dnc", "status", "--dir", str(root)))
    assert code == 0, said
    return next(x for x in said.splitlines() if x.startswith(f"{name}:"))


async def test_a_punch_stopped_at_the_control_ends_said_and_the_machine_is_idle_again(
    served: Shop,  # noqa: F811
) -> None:
    control = served.controls["mill1"]
    control.memory[5000] = surfacing(MOVES)
    root = str(served.root)
    receive = await cellctl("dnc", "receive", "mill1", "--timeout", "600", "--dir", root)
    await wait_state(served, "mill1", "waiting for punch")
    control.punch(5000)
    await punch_under_way(served, "mill1")
    control.set_mode(Mode.MEM)  # the operator turns the mode switch: the punch stops, no DC4
    # Told of the punch that stopped, not "nothing punched" at the end of its --timeout.
    code, said = await finished(receive, 30 + PUNCH_IDLE_S)
    assert code == 3, said
    assert "punch FAILED after " in said and "nothing kept" in said, said
    assert "nothing from the control for" in said and "nothing punched" not in said, said
    # The machine does not stay "punching" (until the punch's hour): it is free again.
    await wait_state(served, "mill1", "idle")
    store = ShopStore(served.root)
    assert any("punch FAILED after " in line for line in store.log_lines("mill1"))
    assert store.received("mill1", None) == []  # a part of a program is not kept as one
    # A whole punch is taken again as ever.
    control.set_mode(Mode.EDIT)
    control.memory[1001] = "O1001 (SHORT)\nG00 X0 Y0\nM30\n"
    receive = await cellctl("dnc", "receive", "mill1", "--timeout", "60", "--dir", root)
    await wait_state(served, "mill1", "waiting for punch")
    control.punch(1001)
    code, said = await finished(receive)
    assert code == 0 and "received O1001" in said, said


async def test_a_punch_under_way_shows_its_characters_never_a_share_of_them(
    served: Shop,  # noqa: F811
) -> None:
    control = served.controls["mill2"]
    control.memory[5000] = surfacing(MOVES)
    control.punch(5000)  # kept as a backup by the server: nobody waits for it
    progress = await punch_under_way(served, "mill2")
    # How far a punch is cannot be known before its DC4: no total, never "done" (100%).
    assert progress["total"] == 0 and progress["fraction"] == 0, progress
    row = await status_row(served.root, "mill2")
    assert row.startswith("mill2: busy: punching | ") and " chars, receiving" in row, row
    assert "%" not in row and not re.search(r"\d+/\d+ chars", row), row
    control.set_mode(Mode.MEM)  # the test is done with it: the punch stops
    await wait_state(served, "mill2", "idle", 30 + PUNCH_IDLE_S)


async def test_serve_stopped_while_a_receive_waits_stops_at_once_and_tells_it(
    shop: Shop,  # noqa: F811
) -> None:
    root = str(shop.root)
    server = await cellctl("dnc", "serve", "--dir", root)
    try:
        await until(lambda: (shop.root / "api.sock").exists(), "dnc serve's API", 30)
        receive = await cellctl("dnc", "receive", "mill1", "--timeout", "600", "--dir", root)
        await wait_state(shop, "mill1", "waiting for punch")
        await shop.close()
        server.send_signal(signal.SIGINT)  # the user's Ctrl-C: no punch has begun
        # It stops now, not when the receive's 600 s are out; the receive is told why.
        code, said = await finished(server, 30)
        assert code in (0, 130), said
        assert "the wait for mill1's punch ended (nothing was punched)" in said, said
        code, said = await finished(receive, 30)
        assert code != 0, said
        assert "the DNC server stopped: the wait for mill1's punch ended" in said, said
    finally:
        if server.returncode is None:
            server.kill()
            await server.wait()
