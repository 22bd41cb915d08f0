"""Bad input on the command line: a one-line reason and exit 2, never a traceback, nothing sent;
and the frictions a new user met. Each case is a defect seen in the field.

A refusal is checked on the real command line in this process (click's runner: the exit
code the shell gets, stdout and stderr apart); what depends on the process (its working
directory) runs ``cellctl`` as a process of its own."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner, Result
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cellctl.ui.cli import main

from .conftest import CELLCTL, emulator_process

ROOT = Path(__file__).resolve().parent.parent


def cellctl(*args: str) -> Result:
    """``cellctl ARGS`` on the real command line, in this process."""
    return CliRunner().invoke(main, list(args))


def cellctl_process(*args: str, cwd: Path, env: dict[str, str]) -> Any:
    """``cellctl ARGS`` in a process of its own, in ``cwd``."""
    return subprocess.run(
        [*CELLCTL, *args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=cwd,
        env={**os.environ, **env},
    )


def one_line_refusal(result: Result, code: int = 2) -> str:
    assert result.exit_code == code, (result.exit_code, result.stdout, result.stderr)
    # An exit with its code, never an exception out of the command (a traceback).
    assert isinstance(result.exception, SystemExit), result.exception
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert 1 <= len(lines) <= 3, result.stderr
    return result.stderr


@pytest.fixture
def compiled(tmp_path: Path) -> Path:
    rec = tmp_path / "load1.rec"
    done = cellctl(
        "robot",
        "compile",
        str(ROOT / "examples" / "robot" / "conveyor_to_cnc1.aml"),
        "-o",
        str(rec),
    )
    assert done.exit_code == 0, done.stderr
    return rec


def test_a_record_with_a_bad_hex_digit(tmp_path: Path, compiled: Path) -> None:
    lines = compiled.read_text().splitlines()
    lines[1] = "D09ZZ012C00C800000000F6"
    bad = tmp_path / "bad.rec"
    bad.write_text("\n".join(lines) + "\n")
    err = one_line_refusal(cellctl("robot", "--link", "loop://", "download", "2", str(bad)))
    assert "bad.rec, line 2: bad hex digit" in err


def test_a_file_whose_first_line_is_not_a_record(tmp_path: Path) -> None:
    bad = tmp_path / "notes.rec"
    bad.write_text("these are my notes\n")
    err = one_line_refusal(cellctl("robot", "--link", "loop://", "download", "1", str(bad)))
    assert "notes.rec, line 1" in err


def test_downloading_a_text_file() -> None:
    # (An AML source is compiled on the way: tests/test_newcomer_refusals.py.)
    path = ROOT / "README.md"
    err = one_line_refusal(cellctl("robot", "--link", "loop://", "download", "1", str(path)))
    assert path.name in err


def test_an_aml_file_that_is_not_utf8(tmp_path: Path) -> None:
    latin = tmp_path / "latin1.aml"
    latin.write_bytes(b"GRASP\n\xff\xfe END\n")
    err = one_line_refusal(cellctl("robot", "compile", str(latin), "-o", str(tmp_path / "o.rec")))
    assert "latin1.aml: not a text file" in err


def test_writing_into_a_missing_directory(tmp_path: Path) -> None:
    aml = ROOT / "examples" / "robot" / "conveyor_to_cnc1.aml"
    err = one_line_refusal(cellctl("robot", "compile", str(aml), "-o", "/nonexistent/dir/x.rec"))
    assert "/nonexistent/dir/x.rec: cannot write" in err
    dyn = ROOT / "examples" / "programs" / "robot_base_rough_cnc1.dyn"
    err = one_line_refusal(cellctl("mill", "preview", str(dyn), "-o", "/nonexistent/dir/x.svg"))
    assert "/nonexistent/dir/x.svg: cannot write" in err


def test_preview_of_a_program_with_errors_exits_1(tmp_path: Path) -> None:
    broken = ROOT / "examples" / "programs" / "broken"
    runner = CliRunner()  # in this process: 16 programs, two commands each
    refused = 0
    for program in sorted(broken.glob("*.dyn")):
        check = runner.invoke(main, ["mill", "check", str(program)])
        svg = str(tmp_path / "p.svg")
        preview = runner.invoke(main, ["mill", "preview", str(program), "-o", svg])
        assert isinstance(preview.exception, SystemExit | None), preview.exception
        if check.exit_code == 1:
            assert preview.exit_code == 1, program.name
            refused += 1
    assert refused > 0


@pytest.mark.parametrize(
    ("kind", "faults"),
    [
        ("robot", ["power-off", "servo-error", "corrupt-checksum", "drop", "silent"]),
        ("mill", ["never-ready", "no-next", "drop", "stall"]),
        ("plc", ["drop", "silent", "stuck-door", "no-pallet", "estop"]),
    ],
)
def test_emulate_help_lists_the_faults(kind: str, faults: list[str]) -> None:
    result = CliRunner().invoke(main, ["emulate", kind, "--help"])
    assert result.exit_code == 0
    for name in faults:
        assert f"  {name}: " in result.output


def test_no_cell_toml_says_so(tmp_path: Path) -> None:
    err = one_line_refusal(cellctl("--cell", str(tmp_path / "cell"), "robot", "status"))
    assert "no " in err and "cell.toml" in err and "known: none" not in err


def test_a_link_command_leaves_no_state_in_the_working_directory(tmp_path: Path) -> None:
    with emulator_process("robot", "--listen", "pty", "--time-scale", "500", "--no-pacing") as url:
        home = tmp_path / "state-home"
        result = cellctl_process(
            "robot", "--link", url, "init", cwd=tmp_path, env={"XDG_STATE_HOME": str(home)}
        )
    assert result.returncode == 0, result.stderr
    assert not (tmp_path / "cell").exists()
    assert list((home / "cellctl" / "state").glob("*.json"))


def test_part_ids_are_shown_and_taken_as_unique_prefixes(tmp_path: Path) -> None:
    from cellctl.cell.journal import open_journal
    from cellctl.mailbox import open_mailbox

    cell = tmp_path / "cell"
    cell.mkdir()
    shutil.copy(ROOT / "examples" / "cell" / "cell.toml", cell / "cell.toml")
    with open_mailbox(cell) as mailbox, open_journal(cell) as journal:
        order, _ = mailbox.post_order("wax-robot-base", 2, order_id="9227175d00c7a1b2c3d4e5")
        parts = journal.create_parts(order)
        journal.hold_part(parts[0].id, "inspect")
    listed = CliRunner().invoke(main, ["--cell", str(cell), "part", "list"], terminal_width=80)
    assert listed.exit_code == 0
    # The whole ids, as reports and events name them; a unique prefix is taken too.
    assert f"{parts[0].id} " in listed.output and f"{parts[1].id} " in listed.output
    released = CliRunner().invoke(main, ["--cell", str(cell), "part", "release", "9227-1"])
    assert released.exit_code == 0, released.output
    assert f"part {parts[0].id} released" in released.output
    ambiguous = CliRunner().invoke(main, ["--cell", str(cell), "part", "scrap", "9227"])
    assert ambiguous.exit_code == 2 and "ambiguous" in ambiguous.output


FILES = st.sampled_from(["README.md", "examples/cell/cell.toml", "/dev/null", "nowhere.rec"])
WORDS = st.sampled_from(
    ["robot", "mill", "compile", "download", "check", "preview", "status", "go", "part",
     "alarm", "submit", "orders", "release", "clear", "--link", "loop://", "-o", "1", "6",
     "x", "--qty", "0", "--cell", "/nonexistent", "cell", "traffic", "machine", "out"]
)  # fmt: skip


# A word of a real command line cannot hold a NUL: exec ends each argument at one.
ARG_TEXT = st.text(st.characters(blacklist_characters="\x00"), max_size=8)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(argv=st.lists(st.one_of(WORDS, FILES, ARG_TEXT), min_size=1, max_size=6))
def test_generated_command_lines_end_in_a_reason_never_a_crash(
    argv: list[str], tmp_path_factory: pytest.TempPathFactory
) -> None:
    cwd = tmp_path_factory.mktemp("argv")
    os.chdir(cwd)
    try:
        argv = [str(ROOT / a) if a in ("README.md", "examples/cell/cell.toml") else a for a in argv]
        result = CliRunner().invoke(main, ["--cell", str(cwd / "cell"), *argv])
    finally:
        os.chdir(ROOT)
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise AssertionError(f"cellctl {' '.join(argv)} crashed") from result.exception


@pytest.mark.parametrize("family", ["robot", "mill"])
def test_a_trace_file_that_cannot_be_written_is_refused_before_the_link(
    family: str, tmp_path: Path
) -> None:
    # Nothing listens at the link: a trace checked after opening it would say so instead.
    trace = str(tmp_path / "no" / "such" / "dir" / "x.log")
    result = cellctl(
        "--cell",
        str(tmp_path),
        family,
        "--trace",
        trace,
        "--link",
        "socket://127.0.0.1:1",
        "status",
    )
    line = one_line_refusal(result)
    assert f"trace file {trace}: cannot write it: No such file or directory" in line


@pytest.mark.parametrize(
    "args",
    [
        ["alarm", "list"],
        ["part", "list"],
        ["cancel", "X"],
        ["plan", "--shift", "1h"],
        ["pause"],
        ["dashboard", "--print"],
    ],
)
def test_a_mistyped_cell_is_refused_and_nothing_is_made_there(
    args: list[str], tmp_path: Path
) -> None:
    mistyped = tmp_path / "mycel"
    line = one_line_refusal(cellctl("--cell", str(mistyped), *args))
    assert f"no cell at {mistyped}: it has no cell.toml" in line
    assert not mistyped.exists()  # no mailbox made, so the next command is refused too


@pytest.mark.parametrize("args", [["robot", "robot", "status"], ["plc", "status"]])
def test_a_cell_toml_that_is_a_fifo_is_refused_not_waited_on(
    args: list[str], tmp_path: Path
) -> None:
    os.mkfifo(tmp_path / "cell.toml")  # opening it to read would wait for a writer for ever
    line = one_line_refusal(cellctl("--cell", str(tmp_path), *args))
    assert f"{tmp_path / 'cell.toml'}: cannot read: a FIFO, not a regular file" in line


def test_an_unknown_machine_is_named_first_with_or_without_a_controller(tmp_path: Path) -> None:
    """``machine NAME out|in`` and ``traffic NAME`` with a name the cell does not have: the
    name is refused, the cell's machines listed, before "no controller runs"."""
    cell = tmp_path / "cell"
    shutil.copytree(ROOT / "examples" / "cell", cell)
    for args in (("machine", "cnc9", "out"), ("machine", "cnc9", "in"), ("traffic", "cnc9")):
        said = one_line_refusal(cellctl("--cell", str(cell), *args))
        assert "unknown machine 'cnc9' (known: robot, cnc1, cnc2)" in said, (args, said)
    # A machine the cell has: the controller is what is missing, said so.
    said = one_line_refusal(cellctl("--cell", str(cell), "machine", "cnc2", "out"))
    assert "no controller runs on" in said and "unknown machine" not in said


def test_a_demo_batch_past_an_orders_most_is_refused(tmp_path: Path) -> None:
    # 100,000 parts made two orders of 50,000: past what an order may hold (10,000).
    result = CliRunner().invoke(main, ["demo", "--parts", "100000", "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    assert "100000 is not in the range 1<=x<=10000" in result.output
    assert not (tmp_path / "o").exists()
