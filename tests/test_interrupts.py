"""Ctrl-C and SIGTERM end every cellctl command the same way, as README's exit codes say:
"interrupted" and 130, once what the command started is ended (a download cut short leaves
the line in step). ``cellctl run`` keeps its own: stopped by SIGTERM, it ends cleanly with 0.
Real ``cellctl`` processes, real signals."""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import signal
import subprocess
from pathlib import Path

from cellctl.emulators.cell import EXAMPLE_CELL
from tests.conftest import CELLCTL, emulated_cell_process, wait_until
from tests.test_robot_interrupt import big_program, paced_robot, robot_command

#: A hang guard, not a timing figure.
GUARD_S = 30.0
#: How long a command may take to come up on a busy box (a Python start, a cell's machines).
STARTED_S = 90.0


async def test_sigterm_ends_a_download_as_ctrl_c_does(tmp_path: Path) -> None:
    """The defect: SIGTERM ended any command run through the shared runner (a download
    here) with 143 and no word, the line left out of step; Ctrl-C said "interrupted", 130."""
    rec = tmp_path / "big.rec"
    rec.write_text(big_program().to_text())
    trace = tmp_path / "download.trace"
    _, server = await paced_robot()
    try:
        link = ("--link", server.url)
        assert (await robot_command(*link, "init"))[0] == 0
        proc = await asyncio.create_subprocess_exec(
            *CELLCTL, "robot", *link, "--trace", str(trace), "download", "4", str(rec),
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        try:
            async with asyncio.timeout(GUARD_S):
                # Mid-way: the N record and a few D records out (one ">>" row a write).
                while not trace.exists() or trace.read_text().count(">>") < 8:
                    assert proc.returncode is None, "the download ended before it was stopped"
                    await asyncio.sleep(0.05)
                proc.send_signal(signal.SIGTERM)
                _, err = await proc.communicate()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        said = err.decode()
        assert proc.returncode == 130, said
        assert said.strip().splitlines()[-1] == "interrupted", said
        # Ended the way Ctrl-C ends it: the download cut short cleanly, the robot answers.
        rc, out, err_text = await robot_command(*link, "status")
        assert rc == 0 and "Robot state" in out, err_text
    finally:
        await server.close()


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
