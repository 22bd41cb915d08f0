"""A part scrapped out of a mill leaves the mill's vise closed: the cell opens it (the robot's
``open_vise_<mill>`` program) before the mill takes its next part, or, without that program,
says so and waits for the vise to be opened by hand. Nothing else is loaded onto the vise
meanwhile, and the batch finishes with no part cut twice."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from cellctl.cell.journal import open_journal
from cellctl.clock import RealClock
from cellctl.mailbox import open_mailbox
from cellctl.service.operator import may_be_in, release_part
from cellctl.testing.rig import CellRig


async def _stall_and_scrap(rig: CellRig) -> str:
    """The finishing cut of order A's first part stalls (held in cnc2's vise); the operator
    fixes cnc2, takes the part out by hand and scraps it saying so. Returns its id."""
    await rig.wait_for(lambda: rig.finished_steps("machine") >= 1, "first cut done")
    rig.switch_on("cnc2:stall")
    [held] = await rig.wait_for(rig.held_parts, "a part held")
    assert held.location == "cnc2"
    await rig.switch_off("cnc2:stall")
    assert rig.cell.take_out("cnc2") is not None
    assert rig.cell.plc.inputs["clamp_closed_2"], "the vise stays as the arm left it"
    await rig.clear_alarms()
    refused = await rig.cli("part", "scrap", held.id)
    assert refused.exit_code != 0 and "may be in cnc2: take it out" in refused.output
    scrapped = await rig.cli("part", "scrap", held.id, "--taken-out")
    assert scrapped.exit_code == 0, scrapped.output
    return held.id


def _into_cnc2_after(rig: CellRig, scrapped: str) -> list[float]:
    """When each transfer into cnc2 of a part other than ``scrapped`` started."""
    return [
        s.started
        for s in rig.journal.steps()
        if s.kind == "transfer" and s.program.endswith("_to_cnc2") and s.part_id != scrapped
    ]


EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
TENDING: dict[str, Any] = {
    "time_scale": 200.0,
    "deadlines": "emulated",
    "cell_options": {"poll_period": 0.1, "read_limit": 2.0},
    "plc_options": {"timeout": 5.0},
}


@pytest.mark.parametrize(
    ("template", "part_type"),
    [("cell", "wax-robot-base"), ("cell-tending", "bracket")],
    ids=["ibm7545-aml", "ur-urscript"],
)
@pytest.mark.virtual
async def test_the_robot_opens_the_vise_of_a_mill_a_scrapped_part_was_taken_out_of(
    tmp_path: Path, template: str, part_type: str
) -> None:
    # The cobot cell as its own tests run it: its machines' time scale and deadlines.
    options = {} if template == "cell" else TENDING
    async with CellRig(tmp_path / "cell", template=EXAMPLES / template, **options) as rig:
        rig.post(part_type, 2, "A")
        controller = await rig.start_controller()
        scrapped = await _stall_and_scrap(rig)
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        parts = rig.journal.parts(order_id="A")
        assert sorted(p.status for p in parts) == ["done", "scrapped"]
        # The vise was opened by the robot's program, then the second part went in.
        [opened] = [e for e in controller.events if "opening cnc2's vise" in e.text]
        assert opened.text.startswith("robot: open_vise_cnc2:")
        [into] = _into_cnc2_after(rig, scrapped)
        assert opened.time <= into
        assert any("cnc2: its vise is open" in e.text for e in controller.events)
        # Every step but the stalled cut ended well: no load waited out its deadline.
        failed = [s for s in rig.journal.steps() if s.state == "failed"]
        assert [(s.machine, s.part_id) for s in failed] == [("cnc2", scrapped)]
        assert not rig.journal.active_alarms() and not rig.cut_twice()
        assert rig.journal.emptied_places() == {}
        assert rig.physical_part("cnc2") is None
        assert rig.cell.outfeed == ["P2"]


@pytest.mark.virtual
async def test_without_the_program_the_mill_waits_for_its_vise_opened_by_hand(
    tmp_path: Path,
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        toml = rig.directory / "cell.toml"
        text = toml.read_text()
        kept = re.sub(r"(?m)^open_vise_cnc\d = .*\n", "", text)
        assert kept != text
        toml.write_text(kept)
        rig.post("wax-robot-base", 2, "A")
        controller = await rig.start_controller()
        scrapped = await _stall_and_scrap(rig)
        [alarm] = await rig.wait_for(lambda: rig.alarms("cnc2", "vise"), "cnc2's vise alarmed")
        assert alarm.text.startswith(f"cnc2's vise is closed with nothing in it (part {scrapped}")
        assert "open it by hand, or give the cell a robot program open_vise_cnc2" in alarm.text
        # The second part, cut on cnc1, is not taken to the closed vise. The operator opens
        # it by hand (the robot's output, from its pendant): the cell goes on.
        await rig.wait_for(
            lambda: any(
                s.machine == "cnc1" and s.state == "finished"
                for s in rig.journal.steps()
                if s.part_id != scrapped and s.kind == "machine"
            ),
            "the second part cut on cnc1",
        )
        await rig.wait_quiet()  # the robot had every chance to take it on
        assert _into_cnc2_after(rig, scrapped) == []
        assert rig.journal.emptied_places() == {"cnc2": scrapped}
        opened_at = rig.journal.clock.now()
        rig.cell.robot.set_output(2, False)
        await rig.wait_for(
            lambda: rig.journal.get_alarm(alarm.id).returned is not None, "the alarm returned"
        )
        await rig.clear_alarms()
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        [into] = _into_cnc2_after(rig, scrapped)
        assert into >= opened_at
        assert not [e for e in controller.events if "opening cnc2's vise" in e.text]
        assert not rig.journal.active_alarms() and not rig.cut_twice()


@pytest.mark.parametrize(
    ("change", "words"),
    [
        # It opens the other mill's vise: cnc2's input never says open.
        (("WRITEO(2, 0)", "WRITEO(1, 0)"), "vise of CNC 2 did not unclamp within 1.5 s"),
        # It opens cnc2's, then waits for an input that never comes: its cycle never ends.
        (("WAITI(6, 1)", "WAITI(6, 1)\n        WAITI(7, 1)"), "output 6 did not go 1"),
    ],
    ids=["vise-stays-closed", "program-never-ends"],
)
@pytest.mark.virtual
async def test_a_vise_program_that_fails_is_alarmed_and_tried_again_once_cleared(
    tmp_path: Path, change: tuple[str, str], words: str
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        program = rig.directory / "robot" / "open_vise_cnc2.aml"
        text = program.read_text()
        assert change[0] in text
        program.write_text(text.replace(*change))
        rig.post("wax-robot-base", 2, "A")
        controller = await rig.start_controller()
        robot = rig.cell.robot

        def tries() -> int:
            return sum("opening cnc2's vise" in e.text for e in controller.events)

        scrapped = await _stall_and_scrap(rig)
        [alarm] = await rig.wait_for(lambda: rig.alarms("cnc2", "vise"), "cnc2's vise alarmed")
        assert alarm.text.startswith("cnc2's vise: robot program open_vise_cnc2 failed: ")
        assert words in alarm.text and "(clear this alarm to try again)" in alarm.text
        await rig.wait_quiet()
        # Tried once, its program stopped (not left waiting on the robot), the robot not
        # counted against.
        assert tries() == 1
        assert not robot.running
        assert controller.machines["robot"].failures == 0
        if change[1] == "WRITEO(1, 0)":
            # The vise still closed: nothing goes into cnc2; cleared, it is tried again.
            assert _into_cnc2_after(rig, scrapped) == []
            assert rig.journal.emptied_places() == {"cnc2": scrapped}
            await rig.clear_alarms()
            await rig.wait_for(lambda: tries() == 2, "the program tried again")
        else:
            # The vise opened all the same: the cell goes on, the alarm returned to normal.
            await rig.wait_for(rig.all_done, "order A done", timeout=60)
            assert rig.journal.get_alarm(alarm.id).returned is not None
            assert rig.journal.emptied_places() == {}


@pytest.mark.parametrize(("at", "emptied"), [("conveyor", ["cnc1"]), ("cnc1", [])])
def test_a_part_released_elsewhere_leaves_the_mill_it_may_have_been_in_emptied(
    tmp_path: Path, at: str, emptied: list[str]
) -> None:
    """A transfer into cnc1 cut short (the arm may have clamped the part there): released at
    the conveyor, the operator's word empties cnc1 (its vise is opened if closed); released
    in cnc1, nothing is emptied."""
    with open_journal(tmp_path, clock=RealClock()) as journal, open_mailbox(tmp_path) as mailbox:
        order, _ = mailbox.post_order("wax-robot-base", 1, order_id="A")
        (part,) = journal.create_parts(order)
        journal.begin_step(part.id, "transfer", "robot", "conveyor_to_cnc1")
        journal.recover()  # a crash mid-transfer: held, may be in cnc1
        assert may_be_in(journal, journal.get_part(part.id)) == ["cnc1"]
        answer = release_part(journal, mailbox, part.id, location=at)
        assert answer["part"]["location"] == at
        assert sorted(journal.emptied_places()) == emptied


@pytest.mark.virtual
async def test_a_scrap_that_lands_while_dispatch_looks_still_opens_the_vise(tmp_path: Path) -> None:
    """Dispatch looks at the work, then (after a read of the PLC) at the emptied vises: a
    scrap that lands in between left that look of the work showing the scrapped part still
    in cnc2. It is no part there again: the vise is still opened before cnc2 takes a part."""
    async with CellRig(tmp_path / "cell", template=EXAMPLES / "cell") as rig:
        rig.post("wax-robot-base", 2, "A")
        controller = await rig.start_controller()
        await rig.wait_for(lambda: rig.finished_steps("machine") >= 1, "first cut done")
        rig.switch_on("cnc2:stall")
        [held] = await rig.wait_for(rig.held_parts, "a part held")
        await rig.switch_off("cnc2:stall")
        assert rig.cell.take_out("cnc2") is not None
        await rig.clear_alarms()
        controller.pause()  # no dispatch of its own meanwhile
        before = controller.workview.current()  # the look from before the scrap
        assert any(p.id == held.id and p.location == "cnc2" for p in before.parts)
        scrapped = await rig.cli("part", "scrap", held.id, "--taken-out")
        assert scrapped.exit_code == 0, scrapped.output
        await controller.read_inputs()
        look = controller.vises.look(before, controller.inputs)
        assert look.to_open == "cnc2" and "cnc2" in rig.journal.emptied_places()
        controller.resume()
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        assert rig.cut_twice() == {} and rig.journal.emptied_places() == {}
        assert any(e.text.startswith("robot: open_vise_cnc2:") for e in controller.events)
        failed = [s for s in rig.journal.steps() if s.state == "failed"]
        assert [(s.machine, s.part_id) for s in failed] == [("cnc2", held.id)]
        await rig.stop_controller()
