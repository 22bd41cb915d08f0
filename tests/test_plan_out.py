"""`cellctl plan --out DIR` writes the plan and a copy of the cell's configuration in
``DIR/cell/``, replacing only a plan's own earlier copy: a real cell there (its journal,
mailbox, machine state, an operator's notes) or a link to one is refused before anything is
written, from a plan and from a replay alike, and nothing is written through a link."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.ui.cli import main

START = "2026-11-25T06:00"
#: A plan that plays little: one part, a quarter of an hour.
PLAN = ["--add", "wax-robot-base:1", "--start", START, "--shift", "15m"]


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("plan-out") / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    return directory


def plan(*args: str, expect: int = 0) -> Result:
    result = CliRunner().invoke(main, ["plan", *args])
    assert result.exit_code == expect, result.output + repr(result.exception)
    return result


def listing(directory: Path) -> dict[str, str]:
    """Every entry under ``directory``: a file's digest, a link's target, a directory."""
    out = {}
    for path in sorted(directory.rglob("*")):
        rel = str(path.relative_to(directory))
        if path.is_symlink():
            out[rel] = f"-> {path.readlink()}"
        elif path.is_file():
            out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            out[rel] = "dir"
    return out


def a_real_cell(where: Path) -> Path:
    """A cell that ran: its configuration, journal, mailbox, machine state and notes."""
    shutil.copytree(EXAMPLE_CELL, where)
    (where / "journal.sqlite3").write_bytes(b"SQLite format 3\x00 a journal")
    (where / "mailbox.sqlite3").write_bytes(b"SQLite format 3\x00 a mailbox")
    (where / "state").mkdir()
    (where / "state" / "cnc1.json").write_text('{"tool": 3}')
    (where / "notes.txt").write_text("cnc2: spindle noise, call service\n")
    return where


def said(result: Result) -> str:
    return " ".join(result.output.split())


@pytest.mark.timeout(300)
def test_a_real_cell_where_the_copy_goes_is_kept_and_refused(cell: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    real = a_real_cell(out / "cell")
    before = listing(out)
    result = plan("--dir", str(cell), *PLAN, "--out", str(out), expect=2)
    text = said(result)
    assert f"{real}: not a plan's copy of a cell's configuration" in text, text
    assert "journal.sqlite3" in text and "mailbox.sqlite3" in text and "state/" in text
    assert "notes.txt" in text and "give --out a directory of its own" in text
    assert "plan of" not in result.stdout
    assert listing(out) == before  # nothing removed, nothing written beside it


@pytest.mark.timeout(300)
def test_a_cells_configuration_alone_is_not_taken_for_a_plans_copy(
    cell: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    shutil.copytree(EXAMPLE_CELL, out / "cell")  # a cell that never ran: still someone's
    before = listing(out)
    text = said(plan("--dir", str(cell), *PLAN, "--out", str(out), expect=2))
    assert "no .cellctl-plan-copy in it, no plan's inputs.json" in text, text
    assert listing(out) == before


@pytest.mark.timeout(300)
def test_no_copy_is_written_through_a_link(cell: Path, tmp_path: Path) -> None:
    other = a_real_cell(tmp_path / "other")
    out = tmp_path / "out"
    out.mkdir()
    (out / "cell").symlink_to(other)
    before = listing(other)
    text = said(plan("--dir", str(cell), *PLAN, "--out", str(out), expect=2))
    assert f"{out / 'cell'}: a symbolic link (to {other})" in text, text
    assert listing(other) == before and sorted(p.name for p in out.iterdir()) == ["cell"]
    # Nor a plan's file: a link where plan.json goes is refused, its target untouched.
    (out / "cell").unlink()
    (out / "plan.json").symlink_to(other / "notes.txt")
    text = said(plan("--dir", str(cell), *PLAN, "--out", str(out), expect=2))
    assert f"{out / 'plan.json'}: in the way of the plan's file" in text, text
    assert listing(other) == before


@pytest.mark.timeout(300)
def test_a_plans_own_output_is_replaced_and_a_replay_is_refused_as_a_plan_is(
    cell: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    plan("--dir", str(cell), *PLAN, "--out", str(out))
    copy = out / "cell"
    assert (copy / ".cellctl-plan-copy").is_file() and (copy / "cell.toml").is_file()
    toml = (copy / "cell.toml").read_text()
    (copy / "cell.toml").write_text(toml + "# an older plan's\n")
    # Written again there: its own copy replaced, as it was.
    plan("--dir", str(cell), *PLAN, "--add", "wax-robot-base:2", "--out", str(out))
    assert (copy / "cell.toml").read_text() == toml
    assert len(json.loads((out / "inputs.json").read_text())["orders"]) == 2
    # A file its copy would not hold (someone's, put there since) is not removed with it.
    (copy / "programs" / "mine.nc").write_text("%\n")
    text = said(plan("--dir", str(cell), *PLAN, "--out", str(out), expect=2))
    assert "it holds programs/mine.nc" in text, text
    (copy / "programs" / "mine.nc").unlink()
    # A copy written before copies were marked: its inputs.json beside it says it is one.
    (copy / ".cellctl-plan-copy").unlink()
    plan("--replay", str(out / "inputs.json"), "--out", str(out))
    # Replayed into its own directory, and into another whose cell/ is a real cell.
    plan("--replay", str(out / "inputs.json"), "--out", str(out))
    elsewhere = tmp_path / "elsewhere"
    real = a_real_cell(elsewhere / "cell")
    before = listing(elsewhere)
    result = plan("--replay", str(out / "inputs.json"), "--out", str(elsewhere), expect=2)
    assert f"{real}: not a plan's copy" in said(result)
    assert listing(elsewhere) == before
    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / "cell").symlink_to(real)
    result = plan("--replay", str(out / "inputs.json"), "--out", str(linked), expect=2)
    assert "a symbolic link" in said(result) and listing(elsewhere) == before
