"""`cellctl resume` while the PLC's emergency stop is pressed: refused in the operator's words,
naming the stop's alarm to clear, with the exit code of a refusal of the cell's state (6, the
cell held: README's exit codes), not the one of a command typed wrong (2)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from cellctl.cell.owner import acquire_controller_lock
from cellctl.errors import MachineInUse, exit_code
from cellctl.service.access import AttachedCell
from cellctl.service.server import ApiServer
from cellctl.testing.rig import CellRig


@pytest.fixture
async def served(tmp_path: Path) -> AsyncIterator[CellRig]:
    """The emulated cell, its controller, and the controller's API on the cell's socket
    (what `cellctl run` serves, and what `cellctl resume` asks)."""
    async with CellRig(tmp_path / "cell") as rig:
        with acquire_controller_lock(rig.directory):  # as `cellctl run` holds it
            controller = await rig.start_controller()
            server = ApiServer(AttachedCell(controller), rig.directory)
            await server.start()
            try:
                yield rig
            finally:
                await server.close()
                await rig.stop_controller()


async def test_resume_while_the_emergency_stop_is_pressed_is_refused_as_a_state(
    served: CellRig,
) -> None:
    rig = served
    controller = rig.controller
    assert controller is not None
    rig.switch_on("plc:estop")
    (alarm,) = await rig.wait_for(lambda: rig.alarms("plc", "estop"), "the stop's alarm")
    await rig.wait_for(lambda: controller.paused, "the cell paused by the stop")
    await rig.wait_for(lambda: not controller.inputs.get("estop_ok", True), "the press seen")

    refused = await rig.cli("resume")

    assert refused.exit_code == exit_code(MachineInUse("")) == 6, refused.output
    said = " ".join(refused.output.split())  # one line, however the terminal wraps it
    assert "the emergency stop is pressed: release it" in said, said
    assert f"clear alarm {alarm.id} (`cellctl alarm clear {alarm.id}`)" in said, said
    assert controller.paused  # nothing started

    # The way out it names: released, the alarm cleared, then resume.
    await rig.switch_off("plc:estop")
    await rig.wait_for(lambda: controller.inputs.get("estop_ok"), "the release seen")
    # Released, its alarm still open: held as well (a release restarts nothing).
    held = await rig.cli("resume")
    assert held.exit_code == 6, held.output
    assert f"the emergency stop's alarm {alarm.id} is not cleared" in held.output, held.output
    assert controller.paused
    cleared = await rig.cli("alarm", "clear", str(alarm.id))
    assert cleared.exit_code == 0, cleared.output
    resumed = await rig.cli("resume")
    assert resumed.exit_code == 0, resumed.output
    assert "resumed" in resumed.output
    assert not controller.paused
