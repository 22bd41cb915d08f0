"""One owner for the PLC too: while a controller runs the cell, ``cellctl plc`` is refused
before a request goes out, naming the holder; with the controller gone it acts again."""

from __future__ import annotations

import asyncio
import subprocess
from pathlib import Path

from cellctl.link.lock import set_process_label
from cellctl.testing.rig import CellRig

from .conftest import CELLCTL


def _plc(cell: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "--cell", str(cell), "plc", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


async def test_plc_commands_are_refused_while_the_controller_owns_the_cell(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        set_process_label("cellctl run")  # what the controller's lock records say
        try:
            await rig.start_controller()
        finally:
            set_process_label(None)
        for args in (["set", "door_2", "1"], ["pulse", "go_1"], ["status"]):
            done = await asyncio.to_thread(_plc, rig.directory, *args)
            assert done.returncode == 6, done.stdout + done.stderr
            assert "plc is in use by" in done.stderr and "(pid " in done.stderr
            assert "use `cellctl console` or the API" in done.stderr
        assert rig.cell.plc.coils["door_2"] is False  # the door did not move
        await rig.stop_controller()
        # The controller gone, the PLC is the command line's again.
        done = await asyncio.to_thread(_plc, rig.directory, "set", "door_2", "1")
        assert done.returncode == 0, done.stderr
        assert rig.cell.plc.coils["door_2"] is True
