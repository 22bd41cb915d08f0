"""A robot fault there as the controller starts: one fault, one alarm, in its cause's words.

The start-up's initialize fails on it first, and the monitor's look at the idle robot sees it
a moment later: both name it by its cause (the robot's status, its link), so the second
sighting is the same alarm (one active alarm per machine and code), not a second one. Once
the fault is gone the robot is initialized by its next transfer and the order finishes.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.testing.rig import CellRig

#: A robot fault switched on before the start, and the one alarm it raises (code, text).
CASES = [
    ("robot:servo-error", "status", "servo error"),
    ("robot:power-off", "status", "power failure"),
    ("robot:silent", "link", "robot not answering"),
]


@pytest.mark.parametrize(("fault", "code", "text"), CASES, ids=[c[0] for c in CASES])
@pytest.mark.virtual
async def test_a_robot_fault_at_start_up_raises_one_alarm(
    tmp_path: Path, fault: str, code: str, text: str
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.switch_on(fault)
        rig.post("wax-robot-base", 1, "A")
        await rig.start_controller()
        await rig.wait_for(lambda: rig.alarms("robot"), "the start-up's alarm")
        # The monitor has looked at the idle robot since, many times: what it saw has been
        # raised by now, if it was going to be.
        await rig.wait_quiet()

        alarms = [(a.machine, a.code, a.text) for a in rig.journal.alarms()]
        assert alarms == [("robot", code, text)], rig.describe()
        assert [r.text for r in rig.reports("alarm-raised")] == [f"robot: {text}"]
        assert not rig.journal.steps(), rig.describe()  # no transfer tried meanwhile

        await rig.switch_off(fault)
        await rig.operator_resolves()
        await rig.wait_for(rig.all_done, "order A done", 300)
        await rig.stop_controller()
        assert rig.cut_twice() == {}, rig.describe()
