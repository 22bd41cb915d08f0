"""A part held in a mill, taken out by hand and scrapped: the cell loads that mill again.

The operator takes the part out of the vise, says so (``cellctl part scrap ID --taken-out``),
switches the fault off and clears the alarm. The vise is still clamped on nothing (the arm
closed it and never opened it again): the next load opens it before it goes in, so the run
finishes without the operator touching the cell again.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.testing.rig import CellRig


@pytest.mark.virtual
async def test_a_part_scrapped_out_of_a_mill_leaves_the_mill_loadable(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 2, "A")
        fault = "cnc2:drop=3"  # cnc2's link drops in the middle of the first part's cut
        switched: list[str] = []

        def switch_as_the_door_opens(name: str, on: bool) -> None:
            if name == "door_1" and on and not switched and rig.finished_steps("machine") >= 1:
                switched.append(fault)
                rig.switch_on(fault)

        rig.cell.plc.hooks.coil.append(switch_as_the_door_opens)
        await rig.start_controller(fail_limit=3, retries=2)
        [held] = await rig.wait_for(rig.held_parts, "a part held in cnc2")
        assert held.location == "cnc2"
        await rig.wait_quiet()
        assert rig.cell.plc.inputs["clamp_closed_2"], "the vise of cnc2 holds the part"
        await rig.switch_off(fault)

        rig.take_out("cnc2")
        refused = await rig.cli("part", "scrap", held.id)
        assert refused.exit_code != 0 and "--taken-out" in refused.output
        scrapped = await rig.cli("part", "scrap", held.id, "--taken-out")
        assert scrapped.exit_code == 0, scrapped.output
        await rig.clear_alarms()

        await rig.wait_for(rig.all_done, "order A done with the part left", timeout=120)
        await rig.stop_controller()

        parts = {p.id: p.status for p in rig.journal.parts()}
        assert sorted(parts.values()) == ["done", "scrapped"], rig.describe()
        assert rig.journal.active_alarms() == [], rig.describe()
        assert rig.cut_twice() == {}, rig.describe()
        assert rig.cell.left_in_vise == [], "a blank clamped over a part"
        # The part left was cut by both mills, in cnc2 after the scrapped one came out.
        assert {"cnc1": 1, "cnc2": 1} in rig.cell.runs_per_part().values(), rig.describe()
