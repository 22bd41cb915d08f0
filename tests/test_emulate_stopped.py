"""Every single-machine `cellctl emulate ...` ends on SIGTERM (as on Ctrl-C) by saying so:
"... stopped", its last line, and exit 0. Each runs in its own process."""

from __future__ import annotations

import subprocess

import pytest

from .conftest import CELLCTL


@pytest.mark.parametrize(
    ("args", "what"),
    [
        (["robot"], "IBM 7545 emulator"),
        (["mill"], "Dyna 2400 mill emulator"),
        (["iso-cnc"], "ISO-code CNC control emulator"),
        (
            ["ur", "--dashboard-port", "0", "--secondary-port", "0", "--rtde-port", "0"],
            "UR emulator",
        ),
    ],
    ids=["robot", "mill", "iso-cnc", "ur"],
)
def test_an_emulator_says_it_stopped(args: list[str], what: str) -> None:
    proc = subprocess.Popen(
        [*CELLCTL, "emulate", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        for row in proc.stdout:
            if "drive it with" in row or "feed it with" in row:  # it serves
                break
        else:
            raise AssertionError(f"cellctl emulate {args[0]} never said how to drive it")
        proc.terminate()
        rest, errors = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 0, errors
    assert rest.splitlines()[-1] == f"{what} stopped", rest + errors
