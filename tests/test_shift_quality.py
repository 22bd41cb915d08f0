"""The shift report's quality counts parts, not steps (ISO 22400's good quantity over produced
quantity): per machine, the parts it worked on that were finished or scrapped in the window,
of which the finished ones are good. A part with many steps counts once; a step that failed
on a part that was then machined again and finished leaves it good.

The journal is built through the real journal API with a clock the test sets.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import pytest

from cellctl.cell.journal import Journal, Part
from cellctl.cell.shift import shift_report
from cellctl.ui.report_cli import shift_csv, shift_lines

from .conftest import SetClock as Clock


@dataclass
class Order:
    id: str
    part_type: str
    qty: int


def _step(journal: Journal, clock: Clock, part: Part, machine: str, program: str,
          state: str = "finished", **kw: str) -> None:  # fmt: skip
    step = journal.begin_step(part.id, "machine" if machine != "robot" else "transfer",
                              machine, program)  # fmt: skip
    clock.at += 10
    journal.end_step(step.id, state, route_index=1, **kw)


@pytest.fixture
def journal(tmp_path: Path) -> tuple[Journal, Clock]:
    clock = Clock()
    return Journal(tmp_path / "journal.sqlite3", clock=clock), clock


def test_quality_is_good_parts_over_parts_finished_or_scrapped(
    journal: tuple[Journal, Clock],
) -> None:
    j, clock = journal
    a, b, c, d = j.create_parts(Order("O", "base", 4))
    # A: two cuts on cnc1 and its transfers, finished.
    for part in (a,):
        _step(j, clock, part, "robot", "in")
        _step(j, clock, part, "cnc1", "rough")
        _step(j, clock, part, "cnc1", "finish")
        _step(j, clock, part, "robot", "out")
        j.finish_part(part.id)
    # B: its cut fails (held), the operator has it cut again, and it is finished: good.
    _step(j, clock, b, "robot", "in")
    _step(j, clock, b, "cnc1", "rough", "failed", outcome="stalled", hold="needs inspection")
    j.release_part(b.id, redo_step=True)
    _step(j, clock, b, "cnc1", "rough")
    _step(j, clock, b, "robot", "out")
    j.finish_part(b.id)
    # C: cut well, then scrapped (the operator found it bad): not good.
    _step(j, clock, c, "robot", "in")
    _step(j, clock, c, "cnc1", "rough")
    j.scrap_part(c.id, "out of tolerance")
    # D: cut twice, neither finished nor scrapped yet: not counted either way.
    _step(j, clock, d, "robot", "in")
    _step(j, clock, d, "cnc1", "rough")
    _step(j, clock, d, "cnc1", "finish")

    report = shift_report(j, ["robot", "cnc1", "cnc2"], {}, 1000.0, clock.at + 10)
    robot, cnc1, cnc2 = report.machines
    # Steps: cnc1 ended 7 (one failed), the robot 6; parts finished or scrapped: A, B, C.
    assert (cnc1.steps_ended, cnc1.steps_good, robot.steps_ended) == (7, 5, 6)
    assert (cnc1.parts_ended, cnc1.parts_good) == (3, 2)
    assert cnc1.quality == round(2 / 3, 4)  # not 5 good steps of 7
    assert (robot.parts_ended, robot.parts_good, robot.quality) == (3, 2, round(2 / 3, 4))
    assert (cnc2.parts_ended, cnc2.quality, cnc2.oee) == (0, None, None)  # it cut nothing
    assert cnc1.oee == pytest.approx(
        round(cnc1.availability * (cnc1.performance or 0) * (2 / 3), 4), abs=1e-4
    )
    # What the shift lead reads: good parts of parts ended, beside the steps.
    lines = shift_lines(report.as_dict())
    (row,) = [x for x in lines if x.startswith("cnc1 ")]
    assert " 66.7 %" in row and "5/7" in row and "2/3" in row, lines
    rows = list(csv.reader(io.StringIO(shift_csv(report.as_dict()))))
    assert ["machine", "cnc1", "parts_good", "2", "cnc1"] in rows
    assert ["machine", "cnc1", "parts_ended", "3", "cnc1"] in rows

    # A window after B was finished: only C (scrapped) ended in it, on cnc1 and the robot.
    later = shift_report(j, ["cnc1"], {}, clock.at - 45, clock.at + 10).machines[0]
    assert (later.parts_ended, later.parts_good, later.quality) == (1, 0, 0.0)
    j.close()
