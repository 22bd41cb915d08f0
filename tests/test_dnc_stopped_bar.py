"""A DNC transfer stopped before its end: its progress bar's last line says stopped, never
done. Real processes (``cellctl dnc drip``, ``cellctl dnc stop``, ``dnc serve``) against an
emulated control over TCP, through the server and without one."""

from __future__ import annotations

import signal
from pathlib import Path

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
from tests.test_dnc_hand import hand_drip
from tests.test_dnc_server import surfacing
from tests.test_dnc_stop import MOVES, progress_under_way


def last_bar(said: str, program: str) -> str:
    """The progress bar's last line (a pipe gets it once, as the bar stops)."""
    return [line for line in said.splitlines() if line.startswith(program) and "chars" in line][-1]


async def test_a_drip_feed_stopped_by_ctrl_c_ends_its_bar_stopped(
    served: Shop,  # noqa: F811
    tmp_path: Path,
) -> None:
    program = tmp_path / "surface.nc"
    program.write_text(surfacing(MOVES))
    control = served.controls["mill2"]
    control.set_mode(Mode.RMT)
    drip = await cellctl("dnc", "drip", "mill2", str(program), "--dir", str(served.root))
    await wait_state(served, "mill2", "drip-feeding surface.nc")
    control.cycle_start()
    await progress_under_way(served, "mill2")
    drip.send_signal(signal.SIGINT)
    code, said = await finished(drip)
    assert code == 130, said
    bar = last_bar(said, "surface.nc")
    assert " stopped " in f"{bar} " and " done " not in f"{bar} ", said


async def test_a_drip_feed_by_hand_stopped_by_dnc_stop_ends_its_bar_stopped(
    shop: Shop,  # noqa: F811
    tmp_path: Path,
) -> None:
    program = tmp_path / "surface.nc"
    program.write_text(surfacing(MOVES))
    control = shop.controls["mill2"]
    async with hand_drip(shop, program) as drip:  # no server: the link opened by the command
        await until(lambda: control.chars_read > 200, "the drip-feed under way", 30)
        code, said = await finished(await cellctl("dnc", "stop", "mill2", "--dir", str(shop.root)))
        assert code == 0, said
        code, told = await finished(drip, 30)
    assert code == 130, told
    bar = last_bar(told, "surface.nc")
    assert " stopped " in f"{bar} " and " done " not in f"{bar} ", told
