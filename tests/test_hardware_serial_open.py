"""A serial port that cannot be opened: what is in the way, and what to do, in the user's words.

- a port another program holds (a terminal program, another user's cellctl: its flock):
  the refusal says to end it and how to find it, exit code 6 (in use);
- a path that is no serial device (cell.toml's ``link`` pointing at a file, a directory, or a
  device that is no terminal): said so, not pyserial's "Could not configure port: (25,
  'Inappropriate ioctl for device')", exit code 3.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import CELLCTL

#: Seconds a refused command (or the holder's start) may take.
REFUSED_S = 60.0

#: A program that holds a serial device as minicom or another cellctl does (flock), and says
#: so once it does.
HOLDER = """
import fcntl, os, sys
fd = os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY)
fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
print("holding", flush=True)
sys.stdin.read()
"""


@pytest.fixture
def env(tmp_path: Path) -> dict[str, str]:
    run = tmp_path / "run"
    run.mkdir(mode=0o700)
    return {**os.environ, "CELLCTL_RUNTIME_DIR": str(run), "HOME": str(tmp_path)}


def _robot_status(link: str, env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "robot", "--link", link, "status"],
        capture_output=True,
        text=True,
        timeout=REFUSED_S,
        env=env,
        cwd=cwd,
    )


def test_a_port_another_program_holds_says_how_to_find_it(
    env: dict[str, str], tmp_path: Path
) -> None:
    master, slave = os.openpty()
    path = os.ttyname(slave)
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, path],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None
        assert holder.stdout.readline().strip() == "holding"
        done = _robot_status(path, env, tmp_path)
    finally:
        holder.communicate("", timeout=REFUSED_S)
        os.close(slave)
        os.close(master)
    assert done.returncode == 6, done.stderr
    assert f"{path} is in use: another program holds the device exclusively" in done.stderr
    assert f"`fuser -v {path}` names it" in done.stderr


@pytest.mark.parametrize(
    ("make", "kind"),
    [
        ("file", "a regular file"),
        ("directory", "a directory"),
        ("/dev/null", "a device that takes no line settings"),
    ],
)
def test_a_link_that_is_no_serial_device_says_what_it_is(
    make: str, kind: str, env: dict[str, str], tmp_path: Path
) -> None:
    if make == "file":
        link = tmp_path / "ttyUSB0"
        link.write_text("")
    elif make == "directory":
        link = tmp_path / "serial"
        link.mkdir()
    else:
        link = Path(make)
    done = _robot_status(str(link), env, tmp_path)
    assert done.returncode == 3, done.stderr
    assert f"cannot open serial port {link}: it is {kind}, not a serial device" in done.stderr
    assert "Inappropriate ioctl" not in done.stderr
