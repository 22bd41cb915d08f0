"""Flow control as an engineer copies it from a machine's manual into ``--line`` or cell.toml.

- ``4800,7E2,RTSCTS`` is taken as ``rtscts`` is (the parity letter was already taken in
  either case): it used to be "not understood";
- ``4800,7E2,xonxoff`` is refused saying why Xon/Xoff stays off (those bytes are the robot's
  protocol), before the port is opened or a byte goes out, exit code 2.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from cellctl.errors import UsageError
from cellctl.link import LineSettings

from .conftest import CELLCTL

#: Seconds a refused command may take (Python's start, the kinds).
REFUSED_S = 60.0


@pytest.mark.parametrize("text", ["4800,7E2,RTSCTS", "4800,7e2, RtsCts", "4800,7E2,rtscts"])
def test_rtscts_is_taken_in_any_case(text: str) -> None:
    assert LineSettings.parse(text) == LineSettings(4800, 7, "E", 2, rtscts=True)


@pytest.mark.parametrize("text", ["4800,7E2,xonxoff", "9600,8N1,XON/XOFF", "4800,7E2,software"])
def test_xon_xoff_is_refused_saying_why(text: str) -> None:
    with pytest.raises(UsageError, match="Xon/Xoff flow control stays off"):
        LineSettings.parse(text)


def test_xon_xoff_on_the_command_line_is_refused_before_a_byte(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir(mode=0o700)
    master, slave = os.openpty()
    os.set_blocking(master, False)
    line = ["--line", "4800,7E2,xonxoff"]
    try:
        done = subprocess.run(
            [*CELLCTL, "robot", "--link", os.ttyname(slave), *line, "status"],
            capture_output=True,
            text=True,
            timeout=REFUSED_S,
            env={**os.environ, "CELLCTL_RUNTIME_DIR": str(run), "HOME": str(tmp_path)},
            cwd=tmp_path,
        )
        with pytest.raises(BlockingIOError):
            os.read(master, 64)  # nothing was sent
    finally:
        os.close(slave)
        os.close(master)
    assert done.returncode == 2, done.stderr
    assert "Xon/Xoff flow control stays off" in done.stderr
    assert "robot's Xon, Xoff and Ack" in done.stderr
