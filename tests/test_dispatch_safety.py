"""No machine gets work it cannot take: a mill whose setup failed, or that never said ready,
gets no part; the alarm comes before any transfer to it; the part stays unharmed (never held
as "needs inspection"); once the fault is gone the batch finishes without a restart."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import pytest

from cellctl.testing.rig import CellRig


def transfers_into(rig: CellRig, mill: str) -> list[float]:
    return [
        s.started
        for s in rig.journal.steps()
        if s.kind == "transfer" and s.program.endswith(f"_to_{mill}")
    ]


def check_every_part_cut_once_by_each_mill(rig: CellRig, parts: int) -> None:
    assert rig.held_parts() == [], rig.describe()
    assert all("needs inspection" not in s.outcome for s in rig.journal.steps())
    assert all(s.state == "finished" for s in rig.journal.steps() if s.kind == "machine"), (
        rig.describe()
    )
    made = [r for r in rig.cell.runs_per_part().values() if r == {"cnc1": 1, "cnc2": 1}]
    assert len(made) == parts, rig.describe()


@pytest.mark.virtual
async def test_a_mill_whose_setup_failed_gets_no_part_until_it_is_set_up(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 2, "A")
        rig.switch_on("cnc1:drop=5")  # the setup block is cut 5 lines in
        await rig.start_controller()
        alarms = await rig.wait_for(lambda: rig.alarms("cnc1"), "an alarm on cnc1")
        assert re.search(r"(setup|initialize) failed", alarms[0].text), alarms[0].text
        # The drop happened once: recovery sets cnc1 up again and the batch runs through.
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        await rig.stop_controller()
        assert transfers_into(rig, "cnc1")
        assert min(transfers_into(rig, "cnc1")) > alarms[0].raised
        check_every_part_cut_once_by_each_mill(rig, 2)
        assert rig.cut_twice() == {}


@pytest.mark.virtual
async def test_a_stalled_mill_gets_no_part_and_the_batch_finishes_after(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 1, "A")
        rig.switch_on("cnc2:stall")  # after its setup block, RTS never rises
        controller = await rig.start_controller()
        alarms = await rig.wait_for(lambda: rig.alarms("cnc2", "readiness"), "cnc2 not ready")
        assert "not ready" in alarms[0].text, alarms[0].text
        # The part is roughed on cnc1 and waits there: cnc2 cannot take it.
        await rig.wait_for(lambda: rig.finished_steps("machine") >= 1, "the cut on cnc1")
        await rig.wait_for(lambda: not controller._busy(), "the cell idle")
        assert transfers_into(rig, "cnc2") == []
        assert rig.cell.vise[2] is None and rig.cell.vise[1] == "P1"
        await rig.switch_off("cnc2:stall")
        await rig.clear_alarms()  # out of service after its failed setups: the operator's word
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        await rig.stop_controller()
        assert min(transfers_into(rig, "cnc2")) > alarms[0].raised
        check_every_part_cut_once_by_each_mill(rig, 1)


#: One block of 8 inches at the slowest feed the Dyna takes (0.1 in/min): 80 machine minutes.
SLOW_BLOCK = """000 ; ONE SLOW BLOCK
001 TOOL 01
002 TD = .500
003 SP= 4000 RPM
004 SPINDLE ON
005 FR XY = .1
006 GOf X 1.000
007   Y 1.125
008 GR X 4.000
009 GR X -4.000
010 SPINDLE OFF
011 GOf X 0
012   Y 0
"""


async def test_a_mill_left_cutting_at_start_takes_work_once_its_block_ends(tmp_path: Path) -> None:
    """A controller that starts while a mill still runs a block (its last owner was killed)
    leaves it out of the plan, raises nothing, and uses it as soon as the block ends."""
    async with CellRig(tmp_path / "cell") as rig:
        programs = rig.directory / "programs"
        result = await rig.cli("mill", "cnc1", "init", str(programs / "cnc1_setup.dyn"))
        assert result.exit_code == 0, result.output
        # The emulated operator sets the reference zero, then presses NEXT: the mill is set
        # up (state 2) and ready (CTS high). It must be, or the block below is refused.
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 10.0
        while True:
            result = await rig.cli("mill", "cnc1", "status")
            if "CTS high" in result.output and "state 2" in result.output:
                break
            assert loop.time() < deadline, (
                f"cnc1 not set up and ready 10 s after its setup; last status:\n{result.output}"
            )
            await asyncio.sleep(0.1)
        # A block of 80 machine minutes (about 5 s here): still cutting when the controller
        # starts, however slow the box (the cell's own rough block could end before).
        program = programs / "slow_block.dyn"
        program.write_text(SLOW_BLOCK)
        result = await rig.cli("mill", "cnc1", "download", "--no-wait", str(program))
        assert result.exit_code == 0, result.output
        controller = await rig.start_controller()
        assert controller.machines["cnc1"].state == "executing (left running)"
        assert not controller.recovery.usable("cnc1")
        rig.post("wax-robot-base", 1, "A")
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        await rig.stop_controller()
        assert rig.alarms("cnc1") == [], rig.describe()
        check_every_part_cut_once_by_each_mill(rig, 1)
