"""An emergency stop while a mill runs a block longer than the stop waits for it: the mill
cannot take END before its block ends (the source's ``E`` is refused mid-block). Its alarm
says so; once a look finds the mill idle, the alarm returns to normal (the operator sees the
condition is gone and may clear it), and on resume the mill is set up again like a halted
one, before it takes another part.

The example cell on virtual time, its machines at their own speed (time scale 1), so that
a block of the roughing program lasts longer than the stop's wait.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.cell.commands import ESTOP_TIMEOUT
from cellctl.testing.rig import CellRig


@pytest.mark.virtual
async def test_a_block_the_stop_cannot_halt_returns_its_alarm_once_it_ends(
    tmp_path: Path,
) -> None:
    async with CellRig(tmp_path / "cell", time_scale=1.0, deadlines="emulated") as rig:
        rig.post("wax-robot-base", 1, "A")
        controller = await rig.start_controller()
        mill = rig.cell.mills["cnc1"]
        await rig.wait_for(
            lambda: (
                mill.executing
                and any(s.machine == "cnc1" and s.state == "started" for s in rig.journal.steps())
            ),
            "cnc1 executing a block of its cut",
            timeout=3600,
        )
        said = await controller.emergency_stop("test")
        assert f"cnc1 still executes a block after {ESTOP_TIMEOUT:g} s" in said, said
        (alarm,) = rig.alarms("cnc1", "estop")
        assert alarm.returned is None  # the block still runs
        returned = await rig.wait_for(
            lambda: [a for a in rig.alarms("cnc1", "estop") if a.returned is not None],
            "the mill's alarm returned to normal once its block ended",
            timeout=3600,
        )
        assert returned[0].id == alarm.id
        assert returned[0].returned is not None and returned[0].returned > alarm.raised
        # The cut was cut short: its part held, the mill set up again before its next part.
        held = rig.held_parts()
        assert [p.location for p in held] == ["cnc1"], rig.describe()
        assert controller.paused
