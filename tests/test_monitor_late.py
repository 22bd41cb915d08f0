"""A machine that answers late is not a silent one: the monitor shows a read out past
``read_limit`` as not answering (the robot out of the plan) at once, and alarms it only if the
read is still out a poll period after it was sent.

The PLC emulator's ``slow=MS`` switch holds each answer back (a busy PLC or network). The cell
on virtual time through ``mem://``, with the shipped poll period (0.5 s) and a read limit of
0.1 s: an answer 120 ms late is past it, even queued behind the steps' own requests on the
PLC's one connection it is back within the period.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.testing.rig import CellRig

OPTIONS = {"poll_period": 0.5, "read_limit": 0.1}


@pytest.mark.virtual
async def test_answers_late_within_the_poll_period_raise_no_alarm(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell", cell_options=OPTIONS) as rig:
        rig.switch_on("plc:slow=120")  # past the read limit, inside the poll period
        rig.post("wax-robot-base", 1, "A")
        await rig.start_controller()
        await rig.wait_for(rig.all_done, "order A done", timeout=120)
        await rig.stop_controller()
        assert rig.cell.plc.onsets.get("slow") is not None  # the answers went late
        assert rig.journal.alarms() == []
        assert rig.held_parts() == []


@pytest.mark.virtual
async def test_a_read_still_out_a_poll_period_after_is_alarmed_once(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell", cell_options=OPTIONS) as rig:
        rig.switch_on("plc:slow=900")
        await rig.start_controller()

        def not_answering() -> list[object]:
            return [a for a in rig.journal.alarms() if a.text == "PLC not answering"]

        await rig.wait_for(not_answering, "the PLC alarmed as not answering", timeout=10)
        await rig.stop_controller()
        assert len(not_answering()) == 1, rig.journal.alarms()
