"""What a newcomer met on the command line, each a defect an exploratory tester found: a
directory that is no cell taken for one (tokens, OPC UA users), an emulated cell's fault
refused only after its files were written, a demo's --out that cannot be made, an AML source
given to a robot download, commands named that do not exist, and a mistyped kind in
cell.toml said twice, cascading, or leaving a machine out of the console. Each is refused in
words, before anything is written or sent, through the real command line."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import click
import pytest
from click.testing import CliRunner, Result
from hypothesis import given
from hypothesis import strategies as st

from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.emulators.plc import FAULTS as PLC_FAULTS
from cellctl.emulators.switches import check_fault
from cellctl.errors import UsageError
from cellctl.service.token import TOKEN_FILE, add_token
from cellctl.ui.cli import main
from cellctl.ui.common import MachineGroup

from .conftest import CELLCTL, emulator_process

ROOT = Path(__file__).resolve().parent.parent
NO_CELL = "it has no cell.toml and no mailbox"


def cellctl(*args: str, stdin: str | None = None) -> Result:
    """``cellctl ARGS`` on the real command line, in this process."""
    return CliRunner().invoke(main, list(args), input=stdin, env={"COLUMNS": "500"})


def refused(result: Result) -> str:
    """The one-line refusal of a command: exit 2, no traceback; its words, on one line."""
    assert result.exit_code == 2, (result.exit_code, result.stdout, result.stderr)
    assert isinstance(result.exception, SystemExit), result.exception
    return " ".join(result.stderr.split())


def copy_cell(tmp_path: Path) -> Path:
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    return cell


def edit(cell: Path, old: str, new: str) -> None:
    toml = cell / "cell.toml"
    text = toml.read_text(encoding="utf-8")
    assert old in text, old
    toml.write_text(text.replace(old, new, 1), encoding="utf-8")


# -- 1. tokens and the audit trail of a directory that is no cell ----------------------------


@pytest.mark.parametrize(
    "args",
    [
        ("token", "add", "x", "--role", "viewer"),
        ("token", "list"),
        ("token", "revoke", "default"),
        ("audit",),
    ],
    ids=["add", "list", "revoke", "audit"],
)
def test_token_commands_refuse_a_directory_that_is_no_cell(
    tmp_path: Path, args: tuple[str, ...]
) -> None:
    nodir = tmp_path / "nodir"
    said = refused(cellctl("--cell", str(nodir), *args))
    assert f"no cell at {nodir}: {NO_CELL}" in said, said
    assert not nodir.exists()  # nothing made for a mistyped --cell
    # An existing directory that is no cell: the same words, nothing made in it.
    nodir.mkdir()
    said = refused(cellctl("--cell", str(nodir), *args))
    assert f"no cell at {nodir}: {NO_CELL}" in said, said
    assert list(nodir.iterdir()) == []


def test_a_token_is_never_made_with_its_cell_directory(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="no such directory"):
        add_token(tmp_path / "nodir", "ann", "viewer")
    assert not (tmp_path / "nodir").exists()


def test_run_in_a_directory_that_is_no_cell_makes_nothing_there(tmp_path: Path) -> None:
    """The defect: `cellctl --cell empty run` made `empty/state/` (its lock) before it
    refused the missing cell.toml."""
    empty = tmp_path / "empty"
    empty.mkdir()
    said = refused(cellctl("--cell", str(empty), "run", "--no-live"))
    assert (
        said == f"error: {empty}/cell.toml: no such file (create it, or run 'cellctl emulate cell')"
    )
    assert not any(empty.iterdir())


def test_tokens_of_a_cell_and_of_a_directory_a_server_ran_in_are_kept(tmp_path: Path) -> None:
    cell = copy_cell(tmp_path)
    assert cellctl("--cell", str(cell), "token", "add", "ann", "--role", "viewer").exit_code == 0
    listed = cellctl("--cell", str(cell), "token", "list")
    assert listed.exit_code == 0 and "ann" in listed.stdout, listed.stderr
    # A DNC shop (no cell.toml): its server wrote api-token; its tokens are managed here too.
    shop = tmp_path / "shop"
    shop.mkdir()
    (shop / TOKEN_FILE).write_text("t" * 43 + "\n")
    made = cellctl("--cell", str(shop), "token", "add", "ann", "--role", "viewer")
    assert made.exit_code == 0, made.stderr
    assert (shop / "tokens" / "ann").is_file()


# -- 2. an OPC UA user where the users file cannot go ----------------------------------------


def test_opcua_adduser_refuses_a_directory_that_is_no_cell_before_the_password(
    tmp_path: Path,
) -> None:
    nodir = tmp_path / "nodir"
    said = refused(
        cellctl("--cell", str(nodir), "opcua", "adduser", "carl", stdin="secret12\nsecret12\n")
    )
    assert f"no cell at {nodir}: {NO_CELL}" in said, said
    assert "password" not in said  # never asked
    assert not nodir.exists()


def test_opcua_adduser_refuses_a_users_file_it_cannot_write(tmp_path: Path) -> None:
    cell = copy_cell(tmp_path)
    (cell / "cell.toml").write_text(
        (cell / "cell.toml").read_text() + '\n[opcua]\nusers = "secrets/users.toml"\n'
    )
    said = refused(cellctl("--cell", str(cell), "opcua", "adduser", "carl", stdin="s\ns\n"))
    users = cell / "secrets" / "users.toml"
    assert f"{users}: cannot write the OPC UA users there: no directory {users.parent}" in said
    assert "password" not in said
    # A directory there, but no file can be made in it: an OSError, said in words.
    edit(cell, 'users = "secrets/users.toml"', 'users = "/proc/users.toml"')
    said = refused(
        cellctl("--cell", str(cell), "opcua", "adduser", "carl", stdin="secret12\nsecret12\n")
    )
    # Asked: the refusal is the write's.
    assert said.startswith("password for carl (8 characters or more): "), said
    assert "error: /proc/users.toml: cannot write the OPC UA users: " in said, said


# -- 3. an emulated cell's faults, checked before anything is written ------------------------


@pytest.mark.parametrize(
    ("fault", "words"),
    [
        ("cnc1:stal", "fault 'cnc1:stal': unknown fault 'stal' for cnc1; known: "),
        ("cnc3:stall", "fault 'cnc3:stall': no machine 'cnc3' (robot, cnc1, cnc2, plc)"),
        ("plc:jam", "fault 'plc:jam': unknown fault 'jam' for plc; known: drop, silent"),
        ("robot:drop=3", "fault 'robot:drop=3': drop takes no argument, not '3'"),
        ("stall", "fault 'stall': write MACHINE:NAME[=ARG], e.g. cnc1:stall"),
    ],
)
def test_emulate_cell_checks_every_fault_before_writing_anything(
    tmp_path: Path, fault: str, words: str
) -> None:
    f1 = tmp_path / "f1"
    args = ("--cell", str(f1), "emulate", "cell", "--fault", "cnc1:stall", "--fault", fault)
    said = refused(cellctl(*args))
    assert words in said, said
    assert not f1.exists()  # no cell.toml, no programs, no robot.pty
    f1.mkdir()
    refused(cellctl(*args))
    assert list(f1.iterdir()) == []


@given(st.text(max_size=40))
def test_a_fault_switch_is_taken_or_refused_in_words(text: str) -> None:
    tables = {"robot": {"drop": "drop the link"}, "cnc1": {"stall": "..."}, "plc": PLC_FAULTS}
    try:
        machine, name, arg = check_fault(text, tables)
    except UsageError as e:
        assert str(e).startswith("fault "), e
    else:
        assert name in tables[machine] and text.startswith(f"{machine}:")
        assert arg is None or PLC_FAULTS.get(name, "").startswith("=")


# -- 4. a demo's --out that cannot be made --------------------------------------------------


@pytest.mark.parametrize("factory", [(), ("--factory", "2")], ids=["cell", "factory"])
def test_demo_refuses_an_out_it_cannot_make_before_it_runs(
    tmp_path: Path, factory: tuple[str, ...]
) -> None:
    said = refused(cellctl("demo", *factory, "--out", "/proc/demo"))
    assert said.startswith("error: /proc/demo: cannot write the demo's output there: "), said
    (tmp_path / "afile").write_text("")
    out = tmp_path / "afile" / "x"
    said = refused(cellctl("demo", *factory, "--out", str(out)))
    assert f"{out}: cannot write the demo's output there: Not a directory" in said, said


# -- 5. an AML source given to a robot download ---------------------------------------------

AML = ROOT / "examples" / "robot" / "conveyor_to_cnc1.aml"


@pytest.fixture
def robot_url() -> Iterator[str]:
    with emulator_process("robot", "--listen", "pty", "--time-scale", "500", "--no-pacing") as url:
        yield url


def robot(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "--cell", str(tmp_path), "robot", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_a_robot_download_compiles_an_aml_source_on_the_way(robot_url: str, tmp_path: Path) -> None:
    source = tmp_path / "prog.aml"
    shutil.copy(AML, source)
    for step in (["init"], ["download", "1", str(source)]):
        done = robot(tmp_path, "--link", robot_url, *step)
        assert done.returncode == 0, (step, done.stderr)
    assert f"{source}: AML source, compiled on the way (" in done.stderr
    assert not source.with_suffix(".rec").exists()  # nothing written beside it
    status = robot(tmp_path, "--link", robot_url, "status")
    assert "Full (PROG)" in status.stdout, status.stdout


def test_an_aml_source_that_does_not_compile_is_refused_before_a_byte(tmp_path: Path) -> None:
    source = tmp_path / "bad.aml"
    source.write_text("MOVE(\n", encoding="utf-8")
    said = refused(cellctl("robot", "--link", "loop://", "download", "1", str(source)))
    assert said.startswith(f"error: {source}, line 1"), said


def test_a_robot_download_of_aml_source_not_named_aml_says_what_to_do(tmp_path: Path) -> None:
    source = tmp_path / "prog.txt"
    shutil.copy(AML, source)
    said = refused(cellctl("robot", "--link", "loop://", "download", "1", str(source)))
    assert f"{source}, line 1: not a record: " in said, said
    rec = source.with_suffix(".rec")
    assert f"{source} looks like AML source: compile it first (cellctl robot compile " in said
    assert f"{source} -o {rec}), or name it .aml" in said, said


# -- 6, 7. every command the messages and the docs name exists --------------------------------


def _resolves(words: list[str]) -> str | None:
    """The first word of ``cellctl WORDS...`` that is no command (options and their values
    skipped, a group's own arguments taken: ``machine NAME out``; a command's arguments end
    the check); None if all are."""
    command: click.Command = main
    ctx = click.Context(main, info_name="cellctl")
    arguments = 0  # of the group's own (``cellctl mill NAME ...``) taken so far
    takes_value = False
    for word in words:
        if takes_value:
            takes_value = False
            continue
        if word.startswith("-"):
            found = next((p for p in command.params if word.split("=")[0] in p.opts), None)
            takes_value = isinstance(found, click.Option) and not found.is_flag and "=" not in word
            continue
        if not isinstance(command, click.Group):
            return None  # an argument of the command
        sub = command.get_command(ctx, word)
        if sub is None:
            own = [p for p in command.params if isinstance(p, click.Argument)]
            # A machine's group takes its NAME itself (``cellctl mill cnc1 status``).
            if arguments < max(len(own), isinstance(command, MachineGroup)):
                arguments += 1
                continue
            return word
        command, arguments = sub, 0
        ctx = click.Context(sub, info_name=word, parent=ctx)
    return None


def _command_words(text: str) -> list[str]:
    """The words of ``cellctl TEXT`` up to the first placeholder (``NAME``, ``[--link``,
    ``check|preview``, ``{name}``, ``...``)."""
    words = []
    for word in text.split():
        if not re.fullmatch(r"(-{1,2}[a-z][\w-]*(=\S*)?|[a-z0-9][a-z0-9_.-]*)", word):
            break
        words.append(word)
    return words


def test_every_cellctl_command_named_in_src_and_docs_exists() -> None:
    """`cellctl plc write COIL on` (a driver's hint) and `cellctl status` (docs/opcua.md)
    named commands that never were."""
    files = [*(ROOT / "src").rglob("*.py"), *(ROOT / "docs").rglob("*.md")]
    missing = []
    for path in files:
        text = path.read_text(encoding="utf-8", errors="replace")
        for found in re.finditer(r"`cellctl ([^`\n]+)`", text):
            bad = _resolves(_command_words(found.group(1)))
            if bad is not None:
                line = text.count("\n", 0, found.start()) + 1
                missing.append(f"{path.relative_to(ROOT)}:{line}: `cellctl {found.group(1)}`")
    assert missing == [], "\n".join(missing)


# -- 8, 9. a mistyped kind in cell.toml: said once, the same everywhere ------------------------

KIND_TYPO = (
    "[machines.cnc1] kind: 'dyna240' is not one of 'dyna2400', 'ibm7545', 'ibm7547', 'iso-cnc'"
)


def cell_check(cell: Path) -> tuple[int, list[str]]:
    done = cellctl("--cell", str(cell), "cell", "check")
    return done.exit_code, [line for line in done.stdout.splitlines() if line.strip()]


def test_a_mistyped_kind_is_one_problem_said_once(tmp_path: Path) -> None:
    cell = copy_cell(tmp_path)
    edit(cell, 'kind = "dyna2400"', 'kind = "dyna240"')
    code, problems = cell_check(cell)
    assert code == 1
    assert len(problems) == 1, problems
    [problem] = problems
    assert problem.startswith(KIND_TYPO), problem
    assert problem.count("dyna240'") == 1, problem  # the name once, not ", not 'dyna240'"
    assert problem.endswith("(the installed kinds) (line 26)"), problem
    # The mill's own command says the same, not "is a 'dyna240', not a mill".
    said = refused(cellctl("--cell", str(cell), "mill", "cnc1", "status"))
    assert said == f"error: {cell / 'cell.toml'}: {problem}", said


def test_a_missing_link_or_a_mistyped_robot_kind_is_one_problem(tmp_path: Path) -> None:
    cell = copy_cell(tmp_path)
    edit(cell, 'link = "rfc2217://192.0.2.10:7001"', "")
    code, problems = cell_check(cell)
    assert code == 1 and len(problems) == 1, problems
    assert problems[0].startswith("[machines.cnc1] link: missing"), problems
    said = refused(cellctl("--cell", str(cell), "mill", "cnc1", "status"))
    assert said == f"error: {cell / 'cell.toml'}: {problems[0]}", said
    shutil.rmtree(cell)
    cell = copy_cell(tmp_path)
    edit(cell, 'kind = "ibm7545"', 'kind = "ibm754"')
    code, problems = cell_check(cell)
    assert code == 1 and len(problems) == 1, problems  # no "[cell] robot: no robot machine"
    assert problems[0].startswith("[machines.robot] kind: 'ibm754' is not one of"), problems


def test_the_standalone_console_refuses_a_machine_of_an_unknown_kind(tmp_path: Path) -> None:
    """Not a menu without cnc1: one line on stderr, exit 2, before any screen is drawn."""
    cell = copy_cell(tmp_path)
    edit(cell, 'kind = "dyna2400"', 'kind = "dyna240"')
    done = subprocess.run(
        [*CELLCTL, "--cell", str(cell), "console"],
        capture_output=True,
        text=True,
        timeout=30,
        stdin=subprocess.DEVNULL,
        env={**os.environ, "COLUMNS": "500"},
        check=False,
    )
    assert done.returncode == 2, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"error: {cell / 'cell.toml'}: {KIND_TYPO}"), lines
    assert done.stdout == ""
