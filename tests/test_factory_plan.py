"""`cellctl factory plan`: `cellctl plan` over every cell of a factory whose directory is on
this host, each from its own state (here its files: no controller runs), a fault window
given to one cell by name."""

from __future__ import annotations

import json
import shutil
from datetime import datetime, timedelta
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.mailbox import open_mailbox
from cellctl.ui.cli import main
from tests.test_plan_cli import listing

FACTORY = """[factory]
name = "lab factory"

[broker]
url = "mqtt://127.0.0.1:1883"
credentials = "factory.credentials"

[cells.cell1]
prefix = "cellctl/cell1"

[cells.cell2]
prefix = "cellctl/cell2"

[cells.cell3]
prefix = "cellctl/cell3"

[cells.cell4]
prefix = "cellctl/cell4"
"""


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_every_cell_on_this_host_is_planned_from_its_own_orders(tmp_path: Path) -> None:
    plant = tmp_path / "plant"
    plant.mkdir()
    (plant / "factory.toml").write_text(FACTORY, encoding="utf-8")
    for name, part in (("cell1", "wax-robot-base"), ("cell2", "wax-toy-mill-table")):
        shutil.copytree(EXAMPLE_CELL, plant / name)
        with open_mailbox(plant / name) as mailbox:
            mailbox.post_order(part, 1, order_id=f"{name}-A")
    shutil.copytree(EXAMPLE_CELL, plant / "cell3")  # no open orders: not planned, said so
    # cell4 is on another host: no directory here.
    out = tmp_path / "plan-out"
    args = ["factory", "--dir", str(plant), "plan", "--shift", "3m", "--out", str(out)]
    later = (datetime.now() + timedelta(hours=2)).strftime("%H:%M")  # after the 3 min
    result = CliRunner().invoke(main, [*args, "--fault", f"cell2/cnc1:down@{later}"])
    assert result.exit_code == 2 and "opens after the plan ends" in result.output
    result = CliRunner().invoke(main, [*args, "--fault", "cell4/cnc2:down@10:00"])
    assert result.exit_code == 2 and "CELL one of cell1, cell2, cell3" in result.output
    before = {name: listing(plant / name) for name in ("cell1", "cell2", "cell3")}
    result = CliRunner().invoke(main, [*args, "--json"])
    assert result.exit_code == 0, result.output
    plans = json.loads(result.output)
    # Each cell is played on a copy: nothing is written into it (cell3 gets no mailbox).
    assert {name: listing(plant / name) for name in before} == before
    assert sorted(plans) == ["cell1", "cell2", "cell3", "cell4"]
    assert "nothing to plan: no open orders" in plans["cell3"]["refused"]
    assert plans["cell4"]["refused"].startswith("not on this host (no ")
    for name, part in (("cell1", "wax-robot-base"), ("cell2", "wax-toy-mill-table")):
        [report] = plans[name]["plans"]
        assert [(o["order_id"], o["part_type"]) for o in report["orders"]] == [(f"{name}-A", part)]
        assert report["until"] - report["start"] == 180 and report["steps"]
        assert (out / name / "plan.svg").is_file() and (out / name / "inputs.json").is_file()
    # A cell said to be in a directory that holds none: refused, not left out unsaid.
    missing = tmp_path / "nowhere"
    result = CliRunner().invoke(main, [*args, "--cell-dir", f"cell4={missing}"])
    assert result.exit_code == 2
    said = "".join(result.output.split())  # one line however the terminal wraps it
    assert f"--cell-dir'cell4={missing}':nocellthere" in said, result.output
