"""What ``cellctl robot`` says of a controller that answers nothing (switched off, a cable
out, a line at the wrong baud): the silence, then what to check, with the line settings it
used. Two processes, the emulator's ``silent`` fault over TCP."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from .conftest import emulator_process
from .test_robot_cli import robot

CHECK = "check its power, the cable and the line settings"


@pytest.fixture
def silent() -> Iterator[str]:
    """A robot controller that reads every byte and answers none; yields its URL."""
    with emulator_process("robot", "--listen", "socket://127.0.0.1:0", "--fault", "silent") as url:
        yield url


def test_a_silent_controller_says_what_to_check_at_the_default_line(
    silent: str, tmp_path: Path
) -> None:
    result = robot(tmp_path, "--link", silent, "status")
    assert result.returncode == 3, result.stderr
    said = result.stderr.strip()
    assert len(said.splitlines()) == 1, said
    # cellctl's words first, as ever, then what to look at.
    assert f"no answer from the robot controller: {CHECK} (4800,7E2, the controller's" in said
    assert "cell.toml's line, or --line" in said, said


def test_a_silent_controller_names_the_line_settings_of_cell_toml(
    silent: str, tmp_path: Path
) -> None:
    (tmp_path / "cell.toml").write_text(
        f'[machines.robot1]\nkind = "ibm7545"\nlink = "{silent}"\nline = "9600,7E2"\n'
    )
    result = robot(tmp_path, "robot1", "status")
    assert result.returncode == 3, result.stderr
    said = result.stderr.strip()
    assert f"no answer from the robot controller: {CHECK} (9600,7E2 here" in said, said
    assert "the controller's default is 4800,7E2" in said, said
