"""The plan's table of orders as a planner reads it: each order's id whole (two long ids
alike but for their ends read apart), how late in one format, never "late by 0", and the
default policy by its name."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.ui.cli import main


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_long_ids_read_whole_and_lateness_in_one_format(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    orders = tmp_path / "orders.csv"
    # Neither finishes in the plan's five minutes: one is due as it ends, one a minute before.
    orders.write_text(
        "id,part_type,qty,priority,due\n"
        "sehr-lange-auftragsnummer-1,wax-toy-mill-table,1,5,WED 06:05\n"
        "sehr-lange-auftragsnummer-2,wax-toy-mill-table,1,4,WED 06:04\n",
        encoding="utf-8",
    )
    result = CliRunner().invoke(
        main,
        ["plan", "--dir", str(cell), "--orders", str(orders), "--start", "2026-11-25T06:00",
         "--shift", "5m"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    # The default policy named as --policy all names it.
    assert "(policy downstream-first, seed 0, poll 15 s)" in result.output
    lines = {line.split()[0]: line for line in result.output.splitlines() if line.strip()}
    first, second = lines["sehr-lange-auftragsnummer-1"], lines["sehr-lange-auftragsnummer-2"]
    assert first.endswith("late: not finished when due"), first
    assert second.endswith("late by at least 0:01:00"), second
    assert "late by at least 0.0 s" not in result.output and " 0.0 s" not in result.output
