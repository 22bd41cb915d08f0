"""A plan's report names each alarm raised (machine, time, text), the first ten of them in
its text and all in its JSON (plan.json), so a machine down in a plan comes with its cause."""

from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path

from cellctl.cell.config import load_cell
from cellctl.cell.journal import open_journal
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.plan.report import ALARMS_SHOWN, plan_report
from cellctl.plan.run import report_from_dict
from tests.test_demo import _ListClock

T0 = datetime(2026, 11, 25, 6, 0).timestamp()


def _report(tmp_path: Path, alarms: int):  # type: ignore[no-untyped-def]
    now = [T0 + 10.0]
    with open_journal(tmp_path, clock=_ListClock(now)) as journal:
        for n in range(alarms):
            journal.raise_alarm("cnc1", "link", f"mill link closed ({n})")
            now[0] += 60.0
        return plan_report(
            journal, load_cell(EXAMPLE_CELL), [], start=T0, until=T0 + 3600, ended=T0 + 3600
        )


def test_a_few_alarms_are_named_one_by_one(tmp_path: Path) -> None:
    report = _report(tmp_path, 2)
    text = "\n".join(report.lines())
    assert "alarms raised: 2" in text
    assert "alarm: cnc1 at Wed 06:00:10: mill link closed (0)" in text, text
    assert "alarm: cnc1 at Wed 06:01:10: mill link closed (1)" in text, text
    said = json.loads(json.dumps(report.as_dict()))
    assert [(a["machine"], a["code"], a["text"]) for a in said["alarms"]] == [
        ("cnc1", "link", "mill link closed (0)"),
        ("cnc1", "link", "mill link closed (1)"),
    ]
    assert report_from_dict(said).alarms == report.alarms


def test_many_alarms_are_named_up_to_ten_then_counted(tmp_path: Path) -> None:
    report = _report(tmp_path, ALARMS_SHOWN + 3)
    lines = report.lines()
    assert sum(line.startswith("alarm: cnc1 ") for line in lines) == ALARMS_SHOWN
    assert "... and 3 more alarm(s) (--json lists them)" in lines
    assert len(report.as_dict()["alarms"]) == ALARMS_SHOWN + 3
