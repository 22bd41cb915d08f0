"""A mill's setup in doubt while a part is being loaded into it: the part in the vise by the
time the mill is ready again, no setup can run over it, so the cell cuts it only on the
operator's word, and its alarm asks for that word (docs/cell.md, "Watching and recovering").

The example cell on virtual time (docs/clock.md), machines 50 times faster than life: a load
lasts long enough for the monitor to see the mill leave READY while the arm is at it.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.testing.rig import CellRig


@pytest.mark.virtual
async def test_a_setup_in_doubt_during_a_load_waits_for_the_operators_word(
    tmp_path: Path,
) -> None:
    async with CellRig(tmp_path / "cell", time_scale=50.0) as rig:
        switched: list[str] = []

        def lose_ready_as_the_door_opens(name: str, on: bool) -> None:
            # The load into CNC 1 has begun (its door opens before the arm moves).
            if name == "door_1" and on and not switched and rig.finished_steps("machine") == 0:
                switched.append("cnc1:never-ready")
                rig.switch_on("cnc1:never-ready")

        rig.cell.plc.hooks.coil.append(lose_ready_as_the_door_opens)
        rig.post("wax-robot-base", 1, "A")
        controller = await rig.start_controller()
        (alarm,) = await rig.wait_for(
            lambda: rig.alarms("cnc1", "readiness"), "CNC 1's setup in doubt", timeout=120
        )
        await rig.wait_for(
            lambda: rig.physical_part("cnc1"), "the part in CNC 1's vise", timeout=120
        )
        # No setup runs over the part: the alarm promises none, it asks for the check.
        assert "set up again" not in alarm.text, alarm.text
        assert "check its setup at the machine, then acknowledge" in alarm.text, alarm.text
        await rig.switch_off("cnc1:never-ready")  # READY again, at the panel
        view = controller.machines["cnc1"]
        await rig.wait_for(
            lambda: "setup in doubt" in view.state, "CNC 1 ready, waiting for the word"
        )
        assert f"acknowledge alarm {alarm.id}" in view.state, view.state
        assert not controller.recovery.usable("cnc1")
        assert rig.finished_steps("machine") == 0 and not rig.open_steps("machine")
        # The operator checks the setup at the machine and says so: the alarm acknowledged.
        result = await rig.cli("alarm", "ack", str(alarm.id))
        assert result.exit_code == 0, result.output
        await rig.wait_for(rig.all_done, "order A done", timeout=600)
        events = [e.text for e in controller.events]
        assert "cnc1: ready again, its setup kept on the operator's word" in events, events
        assert rig.cut_twice() == {}
        await rig.stop_controller()
