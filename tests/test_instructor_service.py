"""An instructor's faults on a running cell, put back as the docs say (docs/cell.md).

A mill that never gets ready while idle is taken out of service after ``fail_limit`` failed
setups; once the instructor switches the fault off, the operator clears the out-of-service
alarm (``cellctl alarm clear ID`` puts it back in service, says docs/cell.md) and the mill
works again: its other alarm (the readiness it lost) returns once it is set up again.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.testing.rig import CellRig
from tests.test_cell_faults import resolve_until_done


@pytest.mark.virtual
async def test_clearing_the_out_of_service_alarm_puts_the_mill_back(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 2, "A")
        controller = await rig.start_controller(fail_limit=2)
        await rig.wait_for(lambda: rig.finished_steps("machine") >= 2, "both mills cut once")
        await rig.wait_quiet()
        rig.switch_on("cnc1:never-ready")
        await rig.wait_for(lambda: rig.alarms("cnc1", "out-of-service"), "cnc1 out of service")
        out = rig.alarms("cnc1", "out-of-service")[0]
        # Its lost readiness is alarmed too: the fault's own alarm, left to the cell.
        assert [a.code for a in rig.alarms("cnc1") if a.id != out.id]
        await rig.switch_off("cnc1:never-ready")
        result = await rig.cli("alarm", "clear", str(out.id))
        assert result.exit_code == 0, result.output
        await rig.wait_for(lambda: controller.machines["cnc1"].in_service, "cnc1 back in service")
        await rig.wait_for(
            lambda: all(a.returned is not None for a in rig.alarms("cnc1")),
            "cnc1's alarms returned to normal",
        )
        rig.post("wax-robot-base", 1, "B")  # and it cuts again
        await resolve_until_done(rig)
        await rig.stop_controller()
        assert rig.journal.machines_out_of_service() == {}
        assert rig.cut_twice() == {}
        assert rig.cell.runs_per_part()["P3"] == {"cnc1": 1, "cnc2": 1}
