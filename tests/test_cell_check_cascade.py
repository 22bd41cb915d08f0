"""``cellctl cell check`` with a bad option on a machine: the option's problems, and the rest
of the cell checked on (the machine stays known with its kind, its programs are checked with
the kind's checker), never a follow-on problem that is not one."""

from __future__ import annotations

import shutil
from pathlib import Path

from cellctl.cell.config import check_cell
from cellctl.emulators.cell import EXAMPLE_CELL

from .test_cell_config import edit

ROOT = Path(__file__).resolve().parent.parent
KERF_CELL = ROOT / "tests" / "plugins" / "kerf_cell"


def copy(template: Path, tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    shutil.copytree(template, directory)
    return directory


def follow_ons(problems: list[str]) -> list[str]:
    return [p for p in problems if "[cell] mills" in p or ".mill:" in p]


def test_a_plug_in_mill_with_bad_options_keeps_its_programs_checked(tmp_path: Path) -> None:
    cell = copy(KERF_CELL, tmp_path)
    edit(
        cell,
        'setup = "programs/saw_setup.cut"',
        'setup = "programs/saw_setup.cut"\noptions = { reply_timeout = -1, colour = "red" }',
    )
    with (cell / "programs" / "bars.cut").open("a", encoding="utf-8") as f:
        f.write("BOGUS 1 2\n")
    config, problems = check_cell(cell)
    assert config is None
    assert any(p.startswith("[machines.saw] options.reply_timeout:") for p in problems), problems
    assert any(p.startswith("[machines.saw] options.colour: unknown key") for p in problems)
    assert any("bars.cut:" in p and "BOGUS" in p for p in problems), problems
    assert follow_ons(problems) == [], problems
    assert len(problems) == 3, problems


def test_a_dyna2400_with_a_bad_option_keeps_its_programs_checked(tmp_path: Path) -> None:
    cell = copy(EXAMPLE_CELL, tmp_path)
    edit(cell, 'go_output = "go_1"', 'go_output = "go_1"\noptions = { ready_wait = "soon" }')
    with (cell / "programs" / "robot_base_rough_cnc1.dyn").open("a", encoding="ascii") as f:
        f.write("G99 junk\n")
    config, problems = check_cell(cell)
    assert config is None
    assert any(p.startswith("[machines.cnc1] options.ready_wait:") for p in problems), problems
    assert any("robot_base_rough_cnc1.dyn:" in p for p in problems), problems
    assert follow_ons(problems) == [], problems
    assert len(problems) == 2, problems


def test_a_bad_option_alone_is_the_only_problem(tmp_path: Path) -> None:
    cell = copy(KERF_CELL, tmp_path)
    edit(
        cell,
        'setup = "programs/saw_setup.cut"',
        'setup = "programs/saw_setup.cut"\noptions = { reply_timeout = -1 }',
    )
    config, problems = check_cell(cell)
    assert config is None
    assert len(problems) == 1 and "options.reply_timeout" in problems[0], problems


def test_a_mill_that_is_not_one_is_said_plainly(tmp_path: Path) -> None:
    cell = copy(EXAMPLE_CELL, tmp_path)
    edit(cell, 'mills = ["cnc1", "cnc2"]', 'mills = ["cnc1", "cnc2", "robot", "cnc7"]')
    _, problems = check_cell(cell)
    said = [p for p in problems if p.startswith("[cell] mills")]
    assert len(said) == 2, problems
    assert "'robot' (kind ibm7545) is not a mill (mill kinds: " in said[0]
    assert "'cnc7': no such machine in [machines]" in said[1]


def test_a_mill_whose_table_is_bad_is_not_said_again(tmp_path: Path) -> None:
    cell = copy(EXAMPLE_CELL, tmp_path)
    edit(cell, 'link = "rfc2217://', 'lnk = "rfc2217://')  # cnc1's table: link missing
    _, problems = check_cell(cell)
    assert any(p.startswith("[machines.cnc1] link: missing") for p in problems), problems
    assert follow_ons(problems) == [], problems


def test_a_mill_without_its_setup_is_still_a_mill(tmp_path: Path) -> None:
    cell = copy(EXAMPLE_CELL, tmp_path)
    edit(cell, 'setup = "programs/cnc2_setup.dyn"\n', "")
    _, problems = check_cell(cell)
    assert problems == [
        next(p for p in problems if p.startswith("[machines.cnc2] setup: a mill needs"))
    ], problems
