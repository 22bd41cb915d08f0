"""`cellctl plc status` while a controller runs the cell: the controller holds the PLC's link,
so the PLC is read through its API (`plc.status`, a viewer's read), with the same output as
without a controller; switching a coil by hand stays refused (the controller drives them)."""

from __future__ import annotations

import re
from pathlib import Path

from cellctl.cell.owner import acquire_controller_lock
from cellctl.service.access import AttachedCell
from cellctl.service.server import ApiServer
from cellctl.testing.rig import CellRig


async def test_plc_status_while_the_controller_runs_is_read_through_it(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        controller = await rig.start_controller()
        server = ApiServer(AttachedCell(controller), rig.directory)
        await server.start()
        try:
            with acquire_controller_lock(rig.directory):  # as `cellctl run` holds it
                result = await rig.cli("plc", "status")
                assert result.exit_code == 0, result.output
                assert f"PLC at {controller.plc.url}" in result.output  # type: ignore[union-attr]
                assert re.search(r"estop_ok +1 +@\d+ +emergency stop circuit closed", result.output)
                assert re.search(r"pallet_request +[01] +@0 ", result.output)
                refused = await rig.cli("plc", "set", "door_1", "1")
                assert refused.exit_code == 6, refused.output
                assert "is in use by" in refused.output
            rig.check_running()
        finally:
            await server.close()
