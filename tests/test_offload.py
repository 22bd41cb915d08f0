"""Work a service hands to a worker process (a plan): its answer, its refusal in its own words,
its lower priority, and its end when nobody waits for it any more."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cellctl.errors import CellctlError, UsageError
from cellctl.service.offload import NICE, in_process


def where_and_how_nice(x: int) -> tuple[int, int, int]:
    return os.getpid(), os.nice(0), x * 2


def refuses(what: str) -> None:
    raise UsageError(f"nothing to plan: {what}")


def breaks() -> None:
    raise ZeroDivisionError("division by zero")


def runs_long(pid_file: str) -> None:
    Path(pid_file).write_text(str(os.getpid()))
    time.sleep(120)


async def test_the_work_runs_in_a_process_of_its_own_at_a_lower_priority() -> None:
    pid, nice, doubled = await in_process(where_and_how_nice, 21)
    assert doubled == 42
    assert pid != os.getpid()
    assert nice == min(os.nice(0) + NICE, 19)


async def test_a_refusal_keeps_its_words_and_a_failure_is_named() -> None:
    with pytest.raises(UsageError, match=r"^nothing to plan: no open orders$"):
        await in_process(refuses, "no open orders")
    with pytest.raises(CellctlError, match="breaks failed in its process: ZeroDivisionError"):
        await in_process(breaks)


async def test_work_nobody_waits_for_is_ended(tmp_path: Path) -> None:
    pid_file = tmp_path / "pid"
    task = asyncio.create_task(in_process(runs_long, str(pid_file)))
    deadline = time.monotonic() + 60
    while not pid_file.exists() or not pid_file.read_text():
        assert time.monotonic() < deadline, "the worker never started"
        await asyncio.sleep(0.05)
    pid = int(pid_file.read_text())
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    # Killed and reaped by the time the cancelled call ends: what it wrote may go now.
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_a_process_starts_where_stderr_has_no_descriptor(tmp_path: Path) -> None:
    """A Textual app (the console, planning with no controller running) stands in for stderr
    with a stream whose descriptor is -1: the first worker of a process must start anyway.
    Played in a fresh interpreter, where multiprocessing has not started its helper yet."""
    script = tmp_path / "start.py"
    script.write_text(
        "import asyncio, io, sys\n"
        "from cellctl.service.offload import in_process\n"
        "from tests.test_offload import where_and_how_nice\n"
        "class Captured(io.StringIO):\n"
        "    def fileno(self) -> int:\n"
        "        return -1\n"
        "if __name__ == '__main__':\n"
        "    sys.stderr = Captured()\n"
        "    print(asyncio.run(in_process(where_and_how_nice, 4))[2])\n"
    )
    root = Path(__file__).resolve().parent.parent
    done = subprocess.run(
        [sys.executable, str(script)],
        cwd=root,
        env={**os.environ, "PYTHONPATH": str(root)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "8"
