"""`cellctl emulate mill` says how to drive it, and that command works as printed.

The Dyna 2400 says it is ready on RTS (the host's CTS): over RFC 2217 the line carries it;
a pty or raw TCP carries no modem lines, where the emulator sends its readiness in-band
(DC1/DC3) and the driver must be told so (`--readiness inband`). Its line too, when it is
not the mill's usual one. Each emulator runs in its own process, and the printed command is
run as a user pastes it, with a COMMAND after it."""

from __future__ import annotations

import shlex
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from .conftest import CELLCTL

HINT = "drive it with: "


@contextmanager
def emulated_mill(*args: str) -> Iterator[str]:
    """``cellctl emulate mill ARGS`` in its own process; yields the command it prints."""
    proc = subprocess.Popen(
        [*CELLCTL, "emulate", "mill", "--time-scale", "1000", "--setup-delay", "100", *args],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        command = ""
        for row in proc.stdout:
            if HINT in row:
                command = row.split(HINT, 1)[1].strip()
                break
        assert command, "the emulator did not say how to drive it"
        yield command
    finally:
        proc.terminate()
        proc.wait(timeout=10)


@pytest.mark.parametrize(
    "args",
    [
        [],  # a pty: in-band readiness, by default
        ["--readiness", "inband"],
        ["--listen", "socket://127.0.0.1:0"],
        ["--listen", "rfc2217://127.0.0.1:0"],  # the modem lines: CTS, by default
        ["--listen", "rfc2217://127.0.0.1:0", "--readiness", "inband"],
        ["--line", "115200,8N1"],
    ],
    ids=["pty", "pty-inband", "socket", "rfc2217", "rfc2217-inband", "pty-line"],
)
def test_the_printed_command_drives_the_emulator(tmp_path: Path, args: list[str]) -> None:
    with emulated_mill(*args) as command:
        words = shlex.split(command)
        assert words[:3] == ["cellctl", "mill", "--link"], command
        status = subprocess.run(
            [*CELLCTL, *words[1:], "status"],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=tmp_path,
        )
    assert status.returncode == 0, f"{command} status: {status.stderr}"
    assert "state " in status.stdout, status.stdout


@pytest.mark.parametrize("listen", ["pty", "socket://127.0.0.1:0"])
def test_modem_readiness_where_no_modem_line_goes_is_refused(listen: str) -> None:
    """No driver could see such a mill ready: refused, with the ways that work."""
    done = subprocess.run(
        [*CELLCTL, "emulate", "mill", "--listen", listen, "--readiness", "modem"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    said = " ".join(done.stderr.split())
    assert f"--listen {listen} cannot carry" in said, said
    assert "use --listen rfc2217://127.0.0.1:0, or --readiness inband" in said, said
    assert "listening" not in done.stdout, done.stdout
