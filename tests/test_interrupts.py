"""Ctrl-C and SIGTERM end every cellctl command the same way, as README's exit codes say:
"interrupted" and 130, once what the command started is ended (a download cut short by
SIGTERM: tests/test_robot_interrupt.py). Ctrl-C at a prompt too. ``cellctl run`` keeps its
own: stopped by SIGTERM, it ends cleanly with 0. Real ``cellctl`` processes, real signals."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
from pathlib import Path

from cellctl.emulators.cell import EXAMPLE_CELL
from tests.conftest import CELLCTL, emulated_cell_process, wait_until

#: A hang guard, not a timing figure.
GUARD_S = 30.0
#: How long a command may take to come up on a busy box (a Python start, a cell's machines).
STARTED_S = 90.0


def test_ctrl_c_at_a_prompt_says_interrupted_not_aborted(tmp_path: Path) -> None:
    """Click answered Ctrl-C at a prompt (a password asked) with "Aborted!" and 1."""
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    proc = subprocess.Popen(
        [*CELLCTL, "--cell", str(cell), "opcua", "adduser", "ann"],
        stdin=subprocess.PIPE,  # kept open: the prompt waits for a line
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,  # no terminal: the password is read from stdin
    )
    assert proc.stderr is not None
    stderr = proc.stderr.fileno()
    os.set_blocking(stderr, False)
    said = b""

    def prompted() -> bool:
        nonlocal said
        with contextlib.suppress(BlockingIOError):
            said += os.read(stderr, 4096)
        assert proc.poll() is None, said
        return b"password for ann" in said

    try:
        wait_until(prompted, "the password prompt", STARTED_S)
        proc.send_signal(signal.SIGINT)
        code = proc.wait(GUARD_S)
        os.set_blocking(stderr, True)
        said += proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=GUARD_S)
    text = said.decode()
    assert code == 130, text
    assert text.strip().splitlines()[-1] == "interrupted" and "Aborted!" not in text, text
    assert not (cell / "opcua-users.toml").exists()  # nobody added


def test_cellctl_run_still_ends_cleanly_on_sigterm(tmp_path: Path) -> None:
    """As a service manager expects (README): 0, not the 130 of the other commands."""
    with emulated_cell_process(tmp_path / "cell", "100") as cell:
        log = tmp_path / "run.log"
        with log.open("w") as out:
            run = subprocess.Popen(
                [*CELLCTL, "--cell", str(cell), "run", "--no-live"],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                text=True,
            )
        try:
            wait_until(lambda: "control API on" in log.read_text(), "the controller", STARTED_S)
            run.send_signal(signal.SIGTERM)
            assert run.wait(GUARD_S) == 0, log.read_text()
        finally:
            if run.poll() is None:
                run.kill()
                run.wait(GUARD_S)
    assert "interrupted" not in log.read_text()
