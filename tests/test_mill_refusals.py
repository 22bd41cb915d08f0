"""A cut that cannot start for a reason the mill cannot mend: a vise that did not clamp, a
program file broken since the cell started. Neither is retried round after round nor
counted against the mill: the mill waits for the operator (the interlock's alarm cleared;
the file put right and the part released), saying so.

The example cell on virtual time (docs/clock.md).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from cellctl.cell.shift import shift_report
from cellctl.clock import current_clock
from cellctl.testing.rig import CellRig


def machining_failures(rig: CellRig) -> list[object]:
    return [s for s in rig.journal.steps() if s.kind == "machine" and s.state == "failed"]


@pytest.mark.virtual
async def test_a_vise_that_does_not_clamp_stops_that_mill_until_its_alarm_is_cleared(
    tmp_path: Path,
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        opened: list[bool] = []

        def unclamp_as_the_cut_begins(name: str, on: bool) -> None:
            # The part's clamp lets go as the mill's door closes behind the robot (a sensor
            # failed, a part taken out by hand): the cut finds the vise open.
            if name == "door_1" and not on and not opened:
                opened.append(True)
                rig.cell.plc.set_coil("clamp_1", False)

        rig.cell.plc.hooks.coil.append(unclamp_as_the_cut_begins)
        rig.post("wax-robot-base", 1, "A")
        controller = await rig.start_controller()
        [alarm] = await rig.wait_for(lambda: rig.alarms("plc", "interlock"), "the vise's alarm")
        assert "vise of CNC 1" in alarm.text, alarm.text
        view = controller.machines["cnc1"]
        await rig.wait_for(lambda: f"clear alarm {alarm.id}" in view.state, "cnc1 says why")
        # Many of the interlock's deadlines later: one failed try, no more, and the mill
        # still in service (the PLC's fault is not counted against it).
        await current_clock().sleep(20 * controller.options.interlock_timeout)
        assert len(machining_failures(rig)) == 1, rig.describe()
        assert view.in_service and not controller.recovery.usable("cnc1")
        # The failed try's time was cnc1's (as the shift report counts it), not dropped.
        assert view.busy_s >= controller.options.interlock_timeout, view.busy_s
        # Every transfer waits on the alarm: the robot is down as long (the shift report).
        now = current_clock().now()
        report = shift_report(rig.journal, ["robot"], {}, alarm.raised, now)
        assert report.machines[0].down_s >= 0.99 * (now - alarm.raised), report.machines[0]
        # The operator clamps the part again and clears the alarm: the cut goes on.
        rig.cell.plc.set_coil("clamp_1", True)
        await rig.clear_alarms()
        await rig.wait_for(rig.all_done, "order A done", timeout=3600)
        assert len(machining_failures(rig)) == 1 and not rig.cut_twice()
        await rig.stop_controller()


@pytest.mark.virtual
async def test_a_program_broken_since_the_start_holds_its_part_not_the_mill(
    tmp_path: Path,
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        program = rig.directory / "programs" / "robot_base_rough_cnc1.dyn"
        good = program.read_bytes()
        broken: list[bool] = []

        def break_the_file(name: str, on: bool) -> None:
            # Someone saves a half-edited file while the part is carried to the mill.
            if name == "door_1" and on and not broken:
                broken.append(True)
                program.write_text("this is no program\n")

        rig.cell.plc.hooks.coil.append(break_the_file)
        rig.post("wax-robot-base", 1, "A")
        controller = await rig.start_controller()
        [alarm] = await rig.wait_for(lambda: rig.alarms("cnc1", "program"), "the program's alarm")
        assert "robot_base_rough_cnc1.dyn refused" in alarm.text, alarm.text
        assert "part release A-1 --redo" in alarm.text, alarm.text
        [held] = await rig.wait_for(rig.held_parts, "the part held")
        assert held.location == "cnc1" and "fix the file" in held.note
        await current_clock().sleep(20 * controller.options.poll_period)
        # Tried once; the mill neither faulted nor taken out of service.
        assert len(machining_failures(rig)) == 1, rig.describe()
        assert controller.machines["cnc1"].in_service and not rig.alarms("cnc1", "machining")
        # Put right and released: cut, once.
        program.write_bytes(good)
        await rig.clear_alarms()
        result = await rig.cli("part", "release", held.id, "--redo")
        assert result.exit_code == 0, result.output
        await rig.wait_for(rig.all_done, "order A done", timeout=3600)
        assert not rig.cut_twice()
        await rig.stop_controller()


@pytest.mark.virtual
async def test_a_block_that_runs_on_after_its_step_failed_is_alarmed_again_once_cleared(
    tmp_path: Path,
) -> None:
    """The defect: a stalled mill (its block ended, READY never came) whose alarm the
    operator cleared sat "executing (left running)" with no alarm and no end: the cell made
    nothing and said nothing. Cleared while the block still runs, the fault is alarmed again;
    stopped at the machine (its panel's clear), the cell goes on."""
    async with CellRig(tmp_path / "cell") as rig:
        rig.cell.switch_on_at_cut("cnc2", "stall")
        rig.post("wax-robot-base", 1, "A")
        await rig.start_controller()
        [first] = await rig.wait_for(lambda: rig.alarms("cnc2", "machining"), "the stall")
        assert "still running" in first.text, first.text
        await rig.clear_alarms()  # cleared, the machine not seen to

        def again() -> list[object]:
            return [a for a in rig.journal.active_alarms() if a.machine == "cnc2"]

        [second] = await rig.wait_for(again, "the fault alarmed again")
        assert "its block still runs after its step failed" in second.text, second.text
        # The operator stops it at the machine (the panel's clear), mends the fault, and
        # deals with the part.
        mill = rig.cell.mills["cnc2"]
        mill.clear_fault("stall")
        await mill.operator_clear()
        for _ in range(5):
            if rig.all_done():
                break
            await rig.operator_resolves()
            await rig.wait_for(
                lambda: rig.all_done() or rig.held_parts() or rig.journal.active_alarms(),
                "the order done or the operator needed",
                timeout=600,
            )
        assert rig.all_done(), rig.describe()
        await rig.stop_controller()


@pytest.mark.virtual
async def test_a_block_that_runs_on_after_its_link_was_cut_is_no_second_alarm(
    tmp_path: Path,
) -> None:
    """The mill's line cut mid-block (the device server dropped it): the step fails on its
    link, one alarm; the block runs on and ends by itself, so the cell waits for it without
    telling the operator to stop it at the machine (fault_reaction's link-cut)."""
    async with CellRig(tmp_path / "cell") as rig:
        mill = rig.cell.mills["cnc1"]
        cuts: list[asyncio.Task[None]] = []

        async def cut_mid_block() -> None:
            await rig.wait_for(lambda: mill.executing, "cnc1 executing its block", 600)
            line = rig.cell.servers["cnc1"].current_line
            assert line is not None
            line.drop()

        def as_the_door_closes(name: str, on: bool) -> None:
            if name == "door_1" and not on and not cuts:
                cuts.append(asyncio.ensure_future(cut_mid_block()))

        rig.cell.plc.hooks.coil.append(as_the_door_closes)
        rig.post("wax-robot-base", 1, "A")
        await rig.start_controller()
        await rig.wait_for(lambda: rig.alarms("cnc1", "link"), "the link's alarm", 600)
        await cuts[0]
        await rig.wait_quiet()
        texts = [a.text for a in rig.journal.alarms() if a.machine == "cnc1"]
        assert texts and all("block still runs" not in t for t in texts), texts
        await rig.stop_controller()
