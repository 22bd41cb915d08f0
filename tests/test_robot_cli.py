"""``cellctl robot`` and ``cellctl emulate robot`` as a user runs them: two processes, a real
pty between them; machine NAMEs from cell.toml; exit codes and the source's messages."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.ui.cli import main

from .conftest import CELLCTL, emulator_process

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@pytest.fixture
def emulator() -> Iterator[str]:
    """``cellctl emulate robot`` in its own process on a pty; yields the pty path."""
    with emulator_process("robot", "--listen", "pty", "--time-scale", "500", "--no-pacing") as url:
        assert url.startswith("/dev/")
        yield url


def robot(cell: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "--cell", str(cell), "robot", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_session_by_link_with_trace(emulator: str, tmp_path: Path) -> None:
    rec = tmp_path / "load1.rec"
    compiled = robot(
        tmp_path, "compile", str(EXAMPLES / "robot" / "conveyor_to_cnc1.aml"), "-o", str(rec)
    )
    assert compiled.returncode == 0, compiled.stderr
    assert rec.read_text().startswith("N09")
    early = robot(tmp_path, "--link", emulator, "go", "1")
    assert early.returncode == 5 and "partition empty" in early.stderr
    init = robot(tmp_path, "--link", emulator, "init")
    assert init.returncode == 0 and "Initializing was correct" in init.stdout
    trace = tmp_path / "robot.trace"
    down = robot(tmp_path, "--link", emulator, "--trace", str(trace), "download", "2", str(rec))
    assert down.returncode == 0, down.stderr
    assert "Download was correct" in down.stdout
    assert ">>  4E" in trace.read_text() and "<<  06" in trace.read_text()
    status = robot(tmp_path, "--link", emulator, "status")
    assert "Partition 2" in status.stdout and "Full" in status.stdout
    assert robot(tmp_path, "--link", emulator, "reject").stdout.startswith("Reject status")
    assert robot(tmp_path, "--link", emulator, "io").returncode == 0
    assert robot(tmp_path, "--link", emulator, "halt").returncode == 0


def test_machine_name_from_cell_toml(emulator: str, tmp_path: Path) -> None:
    (tmp_path / "cell.toml").write_text(
        f'[machines.robot1]\nkind = "ibm7545"\nlink = "{emulator}"\n'
    )
    assert robot(tmp_path, "robot1", "home").returncode == 0
    assert "Robot state" in robot(tmp_path, "status").stdout  # the only robot: no NAME needed
    unknown = robot(tmp_path, "robot9", "status")
    assert unknown.returncode == 2 and "unknown robot 'robot9'" in unknown.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--link", "loop://", "go", "6"], "partition must be 1 to 5"),
        (["--link", "loop://", "download", "0", "x.rec"], "partition must be 1 to 5"),
        (["--link", "loop://", "download", "1", "missing.rec"], "could not open file"),
        (["--link", "ftp://x", "status"], "not understood"),
    ],
)
def test_bad_input_is_refused_before_anything_is_sent(args: list[str], message: str) -> None:
    result = CliRunner().invoke(main, ["robot", *args])
    assert result.exit_code == 2
    assert message in result.output


def test_silent_link_is_exit_3_with_one_line(tmp_path: Path) -> None:
    with emulator_process("robot", "--listen", "socket://127.0.0.1:0", "--fault", "silent") as url:
        result = robot(tmp_path, "--link", url, "status")
    assert result.returncode == 3
    assert "no answer from the robot controller" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
