"""A plan of a cell that was running: a machine taken out of service while it cut plays its
cut in flight to its end (and the unload after it), as the cell does, and stays out after."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.cell.journal import open_journal
from cellctl.clock import RealClock
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.mailbox import open_mailbox
from cellctl.ui.cli import main


class Then(RealClock):
    """The journal's clock set back: the cut began ``ago`` seconds before now."""

    def __init__(self, ago: float) -> None:
        super().__init__()
        self.ago = ago

    def now(self) -> float:
        return time.time() - self.ago


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_a_machine_taken_out_mid_cut_finishes_the_cut_in_the_plan(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    with open_mailbox(cell) as mailbox:
        order, _ = mailbox.post_order("wax-robot-base", 1, order_id="W")
        mailbox.set_order_state("W", "accepted")
        mailbox.set_order_state("W", "in-progress")
    # Its finish cut at cnc2 began two minutes ago; cnc2 was then taken out of service
    # (`cellctl machine cnc2 out`: its step in flight finishes first).
    with open_journal(cell, clock=Then(120.0)) as journal:
        (part,) = journal.create_parts(order)
        journal.move_part(part.id, "cnc2", 1)
        journal.begin_step(part.id, "machine", "cnc2", "robot_base_finish_cnc2")
    with open_journal(cell) as journal:
        journal.set_machine_service("cnc2", False, "taken out by the operator")
    result = CliRunner().invoke(main, ["--cell", str(cell), "plan", "--shift", "1h", "--json"])
    assert result.exit_code == 0, result.output
    found = json.loads(result.stdout)
    [report] = found["plans"]
    assert found["inputs"]["out_of_service"] == ["cnc2"]
    steps = [(s["kind"], s["machine"], s["program"], s["state"]) for s in report["steps"]]
    # The cut in flight finishes (taken up where it had gone), the part is unloaded, and
    # nothing else is cut at cnc2: it is out of service.
    assert steps == [
        ("machine", "cnc2", "robot_base_finish_cnc2", "finished"),
        ("transfer", "robot", "cnc2_to_conveyor", "finished"),
    ], steps
    [order_done] = report["orders"]
    assert order_done["finished"] is not None and order_done["made"] == 1
