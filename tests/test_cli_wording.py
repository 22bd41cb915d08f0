"""What the command line says, as a user reads it: ``cellctl kinds`` in a pipe, a family's
command on a kind that has no such function, the console on a shop with no server, a part
scrapped out of one mill or several, a factory's plan of one cell, and a replay whose cell
copy is gone. Each through the real command line."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

from click.testing import CliRunner

from cellctl.cell.journal import open_journal
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.kinds import registry
from cellctl.mailbox import open_mailbox
from cellctl.plan.engine import PlanInputs, PlanOrder
from cellctl.plan.inputs import inputs_dict
from cellctl.ui.cli import main

from .conftest import CELLCTL
from .test_orders_cli import CELL_TOML, AnOrder
from .test_plugin_kind import TEMPLATE

ROOT = Path(__file__).resolve().parent.parent


def cellctl(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """``cellctl ARGS`` as a process, its output in a pipe (never a terminal)."""
    return subprocess.run(
        [*CELLCTL, *args], capture_output=True, text=True, timeout=60, cwd=cwd, check=False
    )


# -- cellctl kinds in a pipe --------------------------------------------------------------------


def test_cellctl_kinds_in_a_pipe_is_one_whole_line_per_kind() -> None:
    done = cellctl("kinds")
    assert done.returncode == 0, done.stderr
    rows = done.stdout.splitlines()
    kinds = registry.kinds()
    assert rows[0].split() == ["kind", "family", "maker", "model", "from"]
    assert len(rows) == 1 + len(kinds), done.stdout
    for kind, row in zip(kinds, rows[1:], strict=True):
        assert kind.origin is not None
        assert row.startswith(f"{kind.name} "), row
        assert f"{kind.maker} " in row and kind.model in row, row
        # as docs/kinds.md shows it: the distribution, then the module, whole
        assert f"{kind.origin.distribution} ({kind.origin.module})" in row, row
    shown = "kerf100   mill    Kerf   100 bar saw  cellctl-saw (cellctl_saw.kind)"
    assert shown.split() in [row.split() for row in rows]
    docs = (ROOT / "docs" / "kinds.md").read_text(encoding="utf-8")
    assert shown in docs


# -- a family's command on a kind without that function ----------------------------------------


def commands_said(refusal: str) -> list[str]:
    """The commands a refusal says the command line has: ``(its commands: a, b; ...)``."""
    found = re.search(r"its commands: ([^;)]*)", refusal)
    assert found is not None, refusal
    return [c.strip() for c in found.group(1).split(",")]


def test_a_mill_command_the_saw_has_no_function_for_names_the_commands_it_has(
    tmp_path: Path,
) -> None:
    cell = tmp_path / "kc"
    shutil.copytree(TEMPLATE, cell)
    # Refused before any link is opened (the template's saw is at 192.0.2.10: no answer).
    refused = cellctl("--cell", str(cell), "mill", "saw", "go")
    assert refused.returncode == 2, refused.stderr
    assert "no mill command 'go' for saw, a kerf100" in refused.stderr, refused.stderr
    offered = commands_said(refused.stderr)
    assert offered == ["status"], refused.stderr
    # What it says the command line has, it has; what it says the console has, it does not.
    for command in offered:
        shown = cellctl("--cell", str(cell), "mill", "saw", command, "--help")
        assert shown.returncode == 0, shown.stderr
    assert "home, cut: in the console or the control API" in refused.stderr
    home = cellctl("--cell", str(cell), "mill", "saw", "home")
    assert home.returncode == 2, home.stderr
    assert "no mill command 'home' for saw, a kerf100" in home.stderr, home.stderr
    assert "home, cut: in the console or the control API" in home.stderr
    # A command reading no machine is left to its own words.
    check = cellctl("--cell", str(cell), "mill", "saw", "check", str(cell / "cell.toml"))
    assert check.returncode == 2 and "`mill check` reads DYNALAN" in check.stderr


def test_a_robot_command_of_another_kind_names_the_commands_the_robot_has() -> None:
    refused = cellctl("robot", "--kind", "ibm7545", "--link", "loop://", "unlock")
    assert refused.returncode == 2, refused.stderr
    assert "no robot command 'unlock' for loop://, an ibm7545" in refused.stderr
    offered = commands_said(refused.stderr)
    assert "unlock" not in offered and {"go", "status", "io set"} <= set(offered)
    for command in offered:
        shown = cellctl("robot", *command.split(), "--help")
        assert shown.returncode == 0, (command, shown.stderr)


# -- the console on a shop with no server -------------------------------------------------------


def test_the_console_on_a_shop_without_its_server_says_how_to_start_it(tmp_path: Path) -> None:
    shop = tmp_path / "shop"
    shop.mkdir()
    (shop / "dnc.toml").write_text('[machines.mill1]\nlink = "rfc2217://192.0.2.10:4001"\n')
    refused = cellctl("console", "--dir", "shop", cwd=tmp_path)
    assert refused.returncode == 2, refused.stderr
    said = refused.stderr
    assert "no server runs on shop: it has no cell.toml but a dnc.toml (DNC server" in said
    assert "start it with `cellctl dnc serve --dir shop`" in said
    assert "no cell in shop" not in said
    # A directory that is neither a cell nor a shop: said as before.
    (tmp_path / "empty").mkdir()
    refused = cellctl("console", "--dir", "empty", cwd=tmp_path)
    assert refused.returncode == 2
    assert "no cell in empty: empty/cell.toml is missing, and no server runs there" in (
        refused.stderr
    )


# -- a part scrapped once taken out -------------------------------------------------------------


def test_scrapped_out_of_one_mill_or_of_either_of_two_the_words_agree(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    cell.mkdir()
    (cell / "cell.toml").write_text(CELL_TOML)
    with open_journal(cell) as journal:
        one, two, *_ = journal.create_parts(AnOrder("A17", "wax-robot", 2))
        journal.move_part(one.id, "cnc1", 0)
        journal.begin_step(one.id, "machine", "cnc1", "ROUGH")
        # in flight from cnc1 to cnc2 when the controller died: in either mill
        journal.move_part(two.id, "cnc1", 0)
        journal.begin_step(two.id, "transfer", "robot", "cnc1_to_cnc2")
        journal.recover()
    runner = CliRunner()
    args = ["--cell", str(cell), "part", "scrap"]
    said = runner.invoke(main, [*args, one.id, "--reason", "gouged", "--taken-out"])
    assert said.exit_code == 0, said.output
    assert "taken out of cnc1, which takes parts again once its vise is open" in " ".join(
        said.output.split()
    )
    said = runner.invoke(main, [*args, two.id, "--reason", "dropped", "--taken-out"])
    assert said.exit_code == 0, said.output
    assert (
        "taken out of cnc1 or cnc2, which take parts again once their vises are open"
        in " ".join(said.output.split())
    )


# -- a factory's plan of one cell ---------------------------------------------------------------


def test_a_factory_plan_of_one_cell_says_one_cell(tmp_path: Path) -> None:
    plant = tmp_path / "plant"
    plant.mkdir()
    (plant / "factory.toml").write_text(  # no [factory] name: the default, "factory"
        '[broker]\nurl = "mqtt://127.0.0.1:1883"\ncredentials = "factory.credentials"\n\n'
        '[cells.cell1]\nprefix = "cellctl/cell1"\n',
        encoding="utf-8",
    )
    shutil.copytree(EXAMPLE_CELL, plant / "cell1")
    with open_mailbox(plant / "cell1") as mailbox:
        mailbox.post_order("wax-toy-mill-table", 1, order_id="cell1-A")
    args = ["factory", "--dir", str(plant), "plan", "--shift", "2m"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "factory: 1 cell planned" in result.output.splitlines()
    assert "factory factory" not in result.output


# -- a replay whose cell copy is gone -----------------------------------------------------------


def test_a_replay_without_its_cell_copy_says_so_and_what_to_do(tmp_path: Path) -> None:
    start = 1_800_000_000.0
    inputs = PlanInputs(
        cell_dir=Path("cell"),
        orders=(PlanOrder("A", "wax-toy-mill-table", 1),),
        start=start,
        until=start + 3600,
    )
    saved = tmp_path / "plan-out" / "inputs.json"
    saved.parent.mkdir()
    saved.write_text(json.dumps(inputs_dict(inputs, ("default",))), encoding="utf-8")
    result = CliRunner().invoke(main, ["plan", "--replay", str(saved)])
    assert result.exit_code == 2, result.output
    said = " ".join(result.output.split())
    assert f"the cell directory it names, {saved.parent / 'cell'}, is missing" in said, said
    assert "a replay plays the copy of the cell's configuration `cellctl plan --out` saved" in said
    assert "emulate cell" not in said
    (saved.parent / "cell").mkdir()  # there, but emptied
    result = CliRunner().invoke(main, ["plan", "--replay", str(saved)])
    assert result.exit_code == 2
    assert f"{saved.parent / 'cell'}, has no cell.toml" in " ".join(result.output.split())
