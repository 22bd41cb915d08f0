"""A Dyna 2400 restarted behind the cell's back while idle: it comes back READY (CTS high) with
no setup, as a mill set up and idle would look. The cell saw it leave READY while idle, so it
trusts the setup no more. With its vise empty it sets the mill up again before the next cut;
with a part in the vise (no setup runs over one) it takes work again only on the operator's
word: the alarm acknowledged once the setup is checked, or the mill returned to service.

The example cell on virtual time (docs/clock.md).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator
from cellctl.testing.rig import CellRig


async def restart_behind_the_cells_back(rig: CellRig, name: str) -> Dyna2400Emulator:
    """Mill ``name`` off (the cell sees it leave READY), on (the backlash check), memory
    cleared, its link mode selected again by its operator: READY, none of its setup kept."""
    mill = rig.cell.mills[name]
    assert isinstance(mill, Dyna2400Emulator)
    mill.power_off()
    await rig.wait_for(
        lambda: rig.alarms(name, "readiness"), "the cell sees the mill leave READY", timeout=60
    )
    mill.power_on()
    mill.clear_memory()
    mill.reference_zero_set = False
    mill.select(mill.auto_mode)
    return mill


@pytest.mark.virtual
async def test_a_dyna2400_restarted_between_two_orders_is_set_up_again(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 1, "A")
        await rig.start_controller()
        await rig.wait_for(rig.all_done, "order A done", timeout=3600)
        runs_before = len(rig.cell.mills["cnc1"].runs)
        cnc1 = await restart_behind_the_cells_back(rig, "cnc1")
        rig.post("wax-robot-base", 1, "B")
        await rig.wait_for(rig.all_done, "order B done", timeout=3600)
        (alarm,) = rig.alarms("cnc1", "readiness")
        assert "lost readiness while idle" in alarm.text, alarm.text
        assert "its setup is in doubt" in alarm.text and "set up again" in alarm.text, alarm.text
        # Set up again (the operator's reference zero) before B's cut went out.
        assert cnc1.runs[runs_before:], rig.describe()
        assert cnc1.reference_zero_set
        assert not rig.cut_twice()
        await rig.stop_controller()


@pytest.mark.virtual
async def test_a_dyna2400_restarted_with_a_part_in_its_vise_waits_for_the_operators_word(
    tmp_path: Path,
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        controller = await rig.start_controller()
        # CNC 2 out of service: the part roughed on CNC 1 stays in its vise, waiting.
        await controller.set_service("cnc2", False, "tool change")
        rig.post("wax-robot-base", 1, "A")
        await rig.wait_for(lambda: rig.finished_steps("machine") == 1, "the roughing done")
        await rig.wait_for(lambda: rig.physical_part("cnc1"), "the part left in CNC 1's vise")
        await restart_behind_the_cells_back(rig, "cnc1")
        (alarm,) = rig.alarms("cnc1", "readiness")
        assert "a part is in its vise" in alarm.text and "acknowledge" in alarm.text, alarm.text
        view = controller.machines["cnc1"]
        await rig.wait_for(
            lambda: "setup in doubt" in view.state, "CNC 1 ready but waiting for the word"
        )
        assert f"acknowledge alarm {alarm.id}" in view.state, view.state
        assert not controller.recovery.usable("cnc1")
        # The operator checks the zero at the machine and says so: the alarm acknowledged.
        result = await rig.cli("alarm", "ack", str(alarm.id))
        assert result.exit_code == 0, result.output
        await rig.wait_for(lambda: controller.recovery.usable("cnc1"), "CNC 1 back in the plan")
        events = [e.text for e in controller.events]
        assert any("on the operator's word" in text for text in events), rig.describe()
        await controller.set_service("cnc2", True)
        await rig.wait_for(rig.all_done, "order A done", timeout=3600)
        assert not rig.cut_twice()
        await rig.stop_controller()
