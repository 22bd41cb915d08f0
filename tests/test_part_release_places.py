"""A held part is released only where the cell can take it up again: refused elsewhere (it
would wait there for ever, and its order with it), before anything is written."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from cellctl.cell.config import load_cell
from cellctl.cell.journal import open_journal
from cellctl.mailbox import open_mailbox
from cellctl.service.machines import load_cell_file
from cellctl.service.operator import CellPlaces
from cellctl.ui.cli import main

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

CELL_TOML = """
[machines.robot]
kind = "ibm7545"
link = "socket://127.0.0.1:9"

[machines.cnc1]
kind = "dyna2400"
link = "socket://127.0.0.1:9"

[machines.cnc2]
kind = "dyna2400"
link = "socket://127.0.0.1:9"

[parts.base]
route = [{ mill = "cnc1", program = "rough.dyn" }, { mill = "cnc2", program = "finish.dyn" }]
"""


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    (tmp_path / "cell.toml").write_text(CELL_TOML)
    return tmp_path


def cellctl(cell: Path, *args: str) -> Result:
    return CliRunner().invoke(main, ["--cell", str(cell), *args], env={"COLUMNS": "200"})


def held(cell: Path, *, order: str = "A", into: str = "cnc1", cuts: int = 0) -> str:
    """A part held after a transfer into ``into`` was cut short (a crash), ``cuts`` done."""
    with open_mailbox(cell) as mailbox, open_journal(cell) as journal:
        posted, _ = mailbox.post_order("base", 1, order_id=order)
        (part,) = journal.create_parts(posted)
        source = ("conveyor", "cnc1", "cnc2")[cuts]
        if cuts:
            journal.move_part(part.id, source, cuts)
        journal.begin_step(part.id, "transfer", "robot", f"{source}_to_{into}")
        journal.recover()
        return part.id


@pytest.mark.parametrize(
    ("at", "cuts", "allowed"),
    [
        ("mars", 0, "conveyor or cnc1"),  # no place of the cell
        ("robot", 0, "conveyor or cnc1"),  # in the gripper: never taken up from there
        ("cnc2", 0, "conveyor or cnc1"),  # not its next mill: never cut there
        ("out", 0, "conveyor or cnc1"),  # on the outfeed with no cut done
        ("conveyor", 1, "cnc1 or cnc2"),  # cut once: the conveyor loads uncut parts only
        ("out", 1, "cnc1 or cnc2"),
    ],
)
def test_a_place_the_cell_never_takes_it_up_from_is_refused_and_nothing_written(
    cell: Path, at: str, cuts: int, allowed: str
) -> None:
    part_id = held(cell, into="cnc2" if cuts else "cnc1", cuts=cuts)
    result = cellctl(cell, "part", "release", part_id, "--at", at)
    assert result.exit_code == 2, result.output
    said = " ".join(result.stderr.split())
    assert f"part {part_id} cannot be released at {at!r}" in said
    assert f"with {cuts} of its 2 cuts done the cell takes it up again only at {allowed}" in said
    with open_journal(cell) as journal, open_mailbox(cell) as mailbox:
        part = journal.get_part(part_id)
        assert (part.status, part.route_index) == ("held", cuts)
        assert mailbox.reports() == []


@pytest.mark.parametrize(("at", "cuts"), [("conveyor", 0), ("cnc1", 0), ("cnc1", 1), ("cnc2", 1)])
def test_where_the_cell_takes_it_up_it_is_released(cell: Path, at: str, cuts: int) -> None:
    part_id = held(cell, into="cnc2" if cuts else "cnc1", cuts=cuts)
    result = cellctl(cell, "part", "release", part_id, "--at", at)
    assert result.exit_code == 0, result.output
    with open_journal(cell) as journal:
        part = journal.get_part(part_id)
        assert (part.status, part.location) == ("waiting", at)


def test_a_part_whose_route_is_done_is_released_on_the_outfeed(cell: Path) -> None:
    part_id = held(cell, into="conveyor", cuts=2)
    assert cellctl(cell, "part", "release", part_id, "--at", "conveyor").exit_code == 2
    result = cellctl(cell, "part", "release", part_id, "--at", "out")
    assert result.exit_code == 0, result.output
    with open_journal(cell) as journal:
        assert journal.get_part(part_id).location == "out"


def test_a_vise_another_part_is_in_is_refused(cell: Path) -> None:
    first = held(cell, order="A")
    assert cellctl(cell, "part", "release", first, "--at", "cnc1").exit_code == 0
    second = held(cell, order="B")
    result = cellctl(cell, "part", "release", second, "--at", "cnc1")
    assert result.exit_code == 2, result.output
    said = " ".join(result.stderr.split())
    assert f"the journal has part {first} in its vise" in said
    assert cellctl(cell, "part", "release", second, "--at", "conveyor").exit_code == 0


@pytest.mark.parametrize("example", ["cell", "cell-modern", "cell-tending"])
def test_the_running_cell_and_its_file_say_the_same_places(example: str) -> None:
    # A controller checks against its config, the CLI without one against cell.toml.
    directory = EXAMPLES / example
    assert CellPlaces.of_config(load_cell(directory)) == CellPlaces.of_file(
        load_cell_file(directory)
    )
