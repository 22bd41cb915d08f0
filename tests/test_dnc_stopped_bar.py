"""A DNC transfer stopped before its end: its progress bar's last line says stopped, never
done. Real processes (``cellctl dnc drip``, ``cellctl dnc stop``) against an emulated control
over TCP, with no server (Ctrl-C through the server: tests/test_dnc_stop.py)."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import until
from tests.test_dnc_cli import Shop, cellctl, finished, shop  # noqa: F401  (shop: a fixture)
from tests.test_dnc_hand import hand_drip
from tests.test_dnc_server import surfacing
from tests.test_dnc_stop import MOVES


def last_bar(said: str, program: str) -> str:
    """The progress bar's last line (a pipe gets it once, as the bar stops)."""
    return [line for line in said.splitlines() if line.startswith(program) and "chars" in line][-1]


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
