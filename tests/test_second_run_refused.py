"""A second ``cellctl demo`` or ``cellctl emulate factory`` where one runs is refused before it
writes or removes anything: exit 6, naming the running one (pid and command), and the first
run's files (its cell.toml, programs, journal, API token, its broker's config and passwords)
stay as they were, with the first still running."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from pathlib import Path
from queue import Queue

from cellctl.ui.emulate_cli import refuse_if_running_in
from tests.conftest import CELLCTL
from tests.test_demo import _lines, _until

#: How long the first run has to come up (the dashboard demo: its whole batch).
UP_S = 90.0
#: How long a refused command has to say so (a Python start-up and the check).
REFUSED_S = 60.0
#: Written by the first run itself while it idles: the broker's log and its autosave (written
#: to ``mosquitto.db.new``, then renamed), SQLite's write-ahead files.
OWN_WRITES = ("mosquitto.log", "mosquitto.db", "mosquitto.db.new", "-wal", "-shm")


def snapshot(top: Path) -> dict[str, tuple[int, int] | None]:
    """Every path under ``top``: a file's or link's size and mtime, a directory's name only."""
    found: dict[str, tuple[int, int] | None] = {}
    for path in sorted(top.rglob("*")):
        st = path.lstat()
        if path.is_dir() and not path.is_symlink():
            found[str(path.relative_to(top))] = None
        elif not path.name.endswith(OWN_WRITES):
            found[str(path.relative_to(top))] = (st.st_size, st.st_mtime_ns)
    return found


class FirstRun:
    """The first run, as a subprocess whose output lines are read as they come."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        self.proc = subprocess.Popen(
            [*CELLCTL, *args],
            cwd=cwd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            env={**os.environ, "COLUMNS": "200"},
        )
        self.lines: Queue[str] = Queue()
        self.seen: list[str] = []
        threading.Thread(target=_lines, args=(self.proc.stdout, self.lines), daemon=True).start()

    def until(self, pattern: str, within: float = UP_S) -> None:
        _until(self.lines, self.seen, pattern, time.monotonic() + within)

    def stop(self) -> None:
        """Ctrl-C, then kill after a deadline."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        assert self.proc.stdout is not None
        self.proc.stdout.close()


def second(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=REFUSED_S,
        stdin=subprocess.DEVNULL,
        env={**os.environ, "COLUMNS": "200"},
    )


def nothing_left_running(where: Path, within: float = 15.0) -> None:
    """No process names ``where`` on its command line (the broker, a cell's controller), and
    nothing holds a lock in it, within ``within`` s."""
    deadline = time.monotonic() + within
    while True:
        left = []
        for proc in Path("/proc").iterdir():
            if proc.name.isdigit() and int(proc.name) != os.getpid():
                try:
                    line = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode()
                except OSError:
                    continue
                if str(where) in line:
                    left.append(f"{proc.name}: {line}")
        if not left:
            break
        assert time.monotonic() < deadline, f"still running: {left}"
        time.sleep(0.2)
    refuse_if_running_in(where)  # MachineInUse if a lock is still held


def assert_refused(args: list[str], cwd: Path, first: FirstRun, command: str) -> None:
    result = second(args, cwd)
    said = result.stdout + result.stderr
    assert result.returncode == 6, said
    assert f"{command} (pid {first.proc.pid})" in said, said
    assert "Traceback" not in said, said


#: What may come second to a running demo (one first run for all: it takes seconds to start).
AFTER_A_DEMO = [
    ["demo", "--no-compare", "--out", "demo-out"],
    ["demo", "--factory", "2", "--parts", "2", "--out", "demo-out"],
    ["emulate", "factory", "--cells", "1", "demo-out"],
    ["--cell", "demo-out/cell", "emulate", "cell"],
]
#: What may come second to a running emulated factory.
AFTER_A_FACTORY = [
    ["emulate", "factory", "--cells", "2", "plant"],
    ["demo", "--no-compare", "--out", "plant"],
    ["demo", "--factory", "2", "--parts", "2", "--out", "plant"],
    ["--cell", "plant/cell1", "emulate", "cell"],
]


def second_runs_leave_the_first_alone(
    tmp_path: Path,
    first_args: list[str],
    up: str,
    held: str,
    files: set[str],
    seconds: list[list[str]],
    command: str,
) -> str:
    """Start ``first_args``; once it says ``up``, every one of ``seconds`` is refused (naming
    ``command``) and the files in ``held`` (``files`` among them) stay as they were. Returns
    what the first run said."""
    where = tmp_path / held
    first = FirstRun(first_args, cwd=tmp_path)
    try:
        first.until(up)
        before = snapshot(where)
        assert files <= set(before), before
        for args in seconds:
            assert_refused(args, tmp_path, first, command)
            assert snapshot(where) == before, args
            assert first.proc.poll() is None, "".join(first.seen)
    finally:
        first.stop()
    nothing_left_running(where)
    return "".join(first.seen)


def test_a_second_run_leaves_a_running_demo_alone(tmp_path: Path) -> None:
    said = second_runs_leave_the_first_alone(
        tmp_path,
        ["demo", "--dashboard", "--no-compare", "--parts", "1", "--time-scale", "1000"],
        r"Ctrl-C stops",  # the batch is done: the cell idles, its files stay
        "demo-out",
        {"cell/cell.toml", "cell/api-token"},
        AFTER_A_DEMO,
        "cellctl demo",
    )
    # A batch of one part names that part only (no "+ 0" of the other type).
    assert "batch: 1 wax-robot-base\n" in said, said


def test_a_second_run_leaves_a_running_emulated_factory_alone(tmp_path: Path) -> None:
    second_runs_leave_the_first_alone(
        tmp_path,
        ["emulate", "factory", "--cells", "1", "--time-scale", "1000", "plant"],
        r"^serving until Ctrl-C",
        "plant",
        {"broker/mosquitto.conf", "broker/passwd", "cell1/cell.toml"},
        AFTER_A_FACTORY,
        "cellctl emulate factory plant",
    )


def test_the_check_holds_nothing_and_finds_nothing_in_a_fresh_directory(tmp_path: Path) -> None:
    refuse_if_running_in(tmp_path / "missing")
    refuse_if_running_in(tmp_path)
    assert list(tmp_path.iterdir()) == []
