"""Stopping ``cellctl plan`` while its policies play in worker processes, as a user does:
Ctrl-C or SIGTERM to cellctl alone, or to its whole process group (a terminal's Ctrl-C, a
service manager, ``timeout``); and the worst case, cellctl killed. Each time no worker is
left behind, and a stopped plan says "interrupted" and exits 130 (README's exit codes).

The same for the pieces under it, from a process of the test's own: a pool of workers left
by an interrupt, and a pool's or a service's worker whose parent is killed.
Real processes and signals throughout; workers are found in /proc (Linux)."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.tasks import spawned_pool
from tests.conftest import CELLCTL, wait_until

#: A hang guard, not a timing figure: how long a stopped command or an orphan may take to go.
GUARD_S = 30.0
#: How long a plan may take to have its workers playing (they start Python, then play).
STARTED_S = 90.0
#: The CPU seconds each worker has used when it counts as playing (its start is well below).
PLAYING_CPU_S = 1.0
#: The policies of ``--policy all`` (its plans compared): one worker each, up to the cores.
POLICIES = 3
#: A plan of a few CPU-seconds a policy: still playing when it is stopped.
PLAN = ("--add", "wax-robot-base:30", "--shift", "2d", "--policy", "all")

TICKS = os.sysconf("SC_CLK_TCK")


def _stat(pid: int) -> list[str] | None:
    """``/proc/PID/stat``'s fields after the command's name (state first), or None if gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2 :].split()


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie is not running: it waits for a parent to reap it)."""
    fields = _stat(pid)
    return fields is not None and fields[0] not in ("Z", "X")


def cpu_seconds(pid: int) -> float:
    fields = _stat(pid)
    return 0.0 if fields is None else (int(fields[11]) + int(fields[12])) / TICKS


def processes() -> Iterator[tuple[int, list[str], str]]:
    """Every running process: pid, its stat fields, its command line."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        pid = int(entry.name)
        fields = _stat(pid)
        if fields is None or not alive(pid):
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        yield pid, fields, cmdline


def in_session(session: int) -> dict[int, str]:
    """The running processes of session ``session`` (a command started in its own): its
    workers, their children, multiprocessing's resource tracker."""
    return {pid: line for pid, fields, line in processes() if int(fields[3]) == session}


def workers_of(parent: int) -> list[int]:
    """The multiprocessing workers ``parent`` spawned (not its resource tracker)."""
    return [
        pid
        for pid, fields, line in processes()
        if int(fields[1]) == parent and "multiprocessing.spawn" in line
    ]


@contextlib.contextmanager
def own_session(args: list[str], env: dict[str, str]) -> Iterator[subprocess.Popen[str]]:
    """``args`` in a session (and process group) of its own, as a terminal starts a command;
    whatever of it is left at the end is killed."""
    proc = subprocess.Popen(
        args,
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        yield proc
    finally:
        for pid in in_session(proc.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.communicate(timeout=GUARD_S)


def nothing_left(session: int) -> None:
    """Every process of ``session`` ends (within the hang guard)."""
    wait_until(lambda: not in_session(session), "every process of the command to end", GUARD_S)


@pytest.fixture
def playing(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], Path]]:
    """``cellctl plan --dir`` of three policies, once its workers are playing; and the
    directory its temporary files go to."""
    workers = min(os.cpu_count() or 1, POLICIES)
    if workers < 2:
        pytest.skip("one core: the policies play one after the other in cellctl itself")
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {**os.environ, "TMPDIR": str(tmp)}
    with own_session([*CELLCTL, "plan", "--dir", str(cell), *PLAN], env) as proc:

        def all_playing() -> bool:
            assert proc.poll() is None, "cellctl plan ended before its workers played"
            busy = [w for w in workers_of(proc.pid) if cpu_seconds(w) >= PLAYING_CPU_S]
            return len(busy) >= workers

        wait_until(all_playing, "the plan's workers to play", STARTED_S)
        yield proc, tmp


def ended(proc: subprocess.Popen[str], how: str) -> tuple[int, str]:
    """``proc``'s exit status and what it said on stderr, once it has ended."""
    try:
        _, err = proc.communicate(timeout=GUARD_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"cellctl plan still runs {GUARD_S:g} s after {how}")
    return proc.returncode, err


@pytest.mark.parametrize(
    ("sig", "to_group"),
    [
        (signal.SIGINT, False),
        (signal.SIGTERM, False),
        (signal.SIGINT, True),
        (signal.SIGTERM, True),
    ],
    ids=["ctrl-c-to-cellctl", "sigterm-to-cellctl", "ctrl-c-in-a-terminal", "sigterm-to-group"],
)
def test_a_stopped_plan_ends_its_workers_says_interrupted_and_exits_130(
    playing: tuple[subprocess.Popen[str], Path], sig: signal.Signals, to_group: bool
) -> None:
    """The defects: Ctrl-C to cellctl alone printed "Aborted!" and never ended (it waited
    for its workers); SIGTERM ended it with 143 at once, its workers left playing with no
    parent; Ctrl-C in a terminal printed "Aborted!" and exited 1."""
    proc, tmp = playing
    workers = workers_of(proc.pid)
    if to_group:
        os.killpg(proc.pid, sig)
    else:
        os.kill(proc.pid, sig)
    code, err = ended(proc, sig.name)
    assert (code, err.strip()) == (130, "interrupted"), err
    assert not [w for w in workers if alive(w)], "a worker outlived cellctl"
    nothing_left(proc.pid)
    assert list(tmp.iterdir()) == []  # the plan's temporary directory removed too


def test_the_workers_of_a_killed_plan_end_by_themselves(
    playing: tuple[subprocess.Popen[str], Path],
) -> None:
    """cellctl killed (no handler runs): its workers notice and end, not play on for nobody
    and then wait forever to hand over their plans."""
    proc, _ = playing
    workers = workers_of(proc.pid)
    proc.kill()
    proc.wait(GUARD_S)  # its output stays open while a worker, which inherited it, runs
    wait_until(lambda: not [w for w in workers if alive(w)], "the orphaned workers to end", GUARD_S)
    nothing_left(proc.pid)


def test_a_pool_left_by_an_interrupt_kills_its_workers_and_waits_for_none_of_its_jobs() -> None:
    with pytest.raises(KeyboardInterrupt), spawned_pool(1) as pool:
        worker = pool.submit(os.getpid).result(timeout=STARTED_S)
        pool.submit(time.sleep, 600)  # a job that would hold a waiting exit for ten minutes
        raise KeyboardInterrupt
    assert not alive(worker)  # killed and reaped before the block was left


#: A pool's worker, busy for ten minutes, in a process of its own.
POOL_SCRIPT = """
import time
from cellctl.tasks import spawned_pool
with spawned_pool(1) as pool:
    pool.submit(time.sleep, 600).result()
"""

#: A service's worker (a plan away from the cell's loop), busy for ten minutes.
SERVICE_SCRIPT = """
import asyncio, time
from cellctl.service.offload import in_process
asyncio.run(in_process(time.sleep, 600))
"""


@pytest.mark.parametrize("script", [POOL_SCRIPT, SERVICE_SCRIPT], ids=["pool", "service"])
def test_a_worker_ends_when_its_parent_is_killed(script: str) -> None:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    with own_session([sys.executable, "-c", script], env) as parent:
        found: list[int] = []

        def started() -> bool:
            assert parent.poll() is None, "the worker's parent ended by itself"
            found[:] = workers_of(parent.pid)
            return bool(found)

        wait_until(started, "the worker to start", STARTED_S)
        parent.kill()
        parent.wait(GUARD_S)
        wait_until(lambda: not alive(found[0]), "the orphaned worker to end", GUARD_S)
        nothing_left(parent.pid)
