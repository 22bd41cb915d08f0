"""What a ``dnc receive`` leaves behind at the server: a receive killed while it waits for
a punch does not keep the machine ``waiting for punch`` until its timeout, and a punch kept
after an error clears that error from ``dnc status`` as a sent program does. Real
processes (``cellctl dnc ...``) against emulated controls on a pty and TCP."""

from __future__ import annotations

import signal

from tests.conftest import until
from tests.test_dnc_cli import (  # noqa: F401  (shop and served are fixtures)
    Shop,
    cellctl,
    finished,
    served,
    shop,
    wait_state,
)
from tests.test_dnc_punch import status_row


async def test_a_receive_killed_while_it_waits_ends_its_wait_at_the_server(
    served: Shop,  # noqa: F811
) -> None:
    root = str(served.root)
    receive = await cellctl("dnc", "receive", "mill1", "--timeout", "600", "--dir", root)
    try:
        await wait_state(served, "mill1", "waiting for punch")
    finally:
        receive.send_signal(signal.SIGKILL)  # no goodbye: its connection just drops
        await finished(receive, 30)
    # Idle again now, not when the dead receive's 600 s are out.
    await wait_state(served, "mill1", "idle", 30)
    # And what the control punches next is kept as a backup, as with nobody waiting.
    control = served.controls["mill1"]
    control.memory[1001] = "O1001 (SHORT)\nG00 X0 Y0\nM30\n"
    control.punch(1001)
    status = await until(
        lambda: (
            (served.root / "mill1" / "received").exists()
            and any((served.root / "mill1" / "received").iterdir())
        ),
        "the punch kept in mill1/received",
        60,
    )
    assert status
    await wait_state(served, "mill1", "idle", 30)


async def test_a_punch_kept_after_a_refused_request_clears_the_last_error(
    served: Shop,  # noqa: F811
) -> None:
    control = served.controls["mill1"]
    root = str(served.root)
    control.memory[9999] = "O9999 (LOAD O7777)\n"  # no O7777 in the shop: refused
    receive = await cellctl("dnc", "receive", "mill1", "--timeout", "60", "--dir", root)
    await wait_state(served, "mill1", "waiting for punch")
    control.punch(9999)
    code, said = await finished(receive)
    assert code == 0 and "refused" in said, said
    row = await status_row(served.root, "mill1")
    assert "last error: request load O7777 refused" in row, row
    # A program punched and kept: the error is behind, as after a program sent.
    control.memory[1001] = "O1001 (SHORT)\nG00 X0 Y0\nM30\n"
    receive = await cellctl("dnc", "receive", "mill1", "--timeout", "60", "--dir", root)
    await wait_state(served, "mill1", "waiting for punch")
    control.punch(1001)
    code, said = await finished(receive)
    assert code == 0 and "received O1001" in said, said
    row = await status_row(served.root, "mill1")
    assert row.startswith("mill1: idle") and "last error" not in row, row
    status = await served.status()
    assert status["machines"]["mill1"]["error"] is None, status["machines"]["mill1"]
