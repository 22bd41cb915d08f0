"""``--listen pty:PATH`` keeps one owner per PATH and never destroys what is there.

Every test runs the real ``cellctl emulate ...`` in its own process, as a user would: a file
or a directory at PATH is refused and kept, a second emulator on a held PATH is refused
naming the first (which still answers there), a link left by a dead emulator is replaced,
and an emulator removes PATH on exit only if it is still its own link.
"""

from __future__ import annotations

import asyncio
import os
import queue
import re
import subprocess
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from cellctl.emulators.cell import EmulatedCell
from cellctl.errors import MachineInUse

from .conftest import CELLCTL

#: Deadlines, s: a command refused before it serves exits at once; an emulator is up in a
#: few seconds, a whole emulated cell (Python start, kinds, PLC, mills) in a few more.
REFUSED_S = 60.0
STARTED_S = 60.0
STOPPED_S = 10.0


@pytest.fixture
def env(tmp_path: Path) -> dict[str, str]:
    """The environment of every cellctl this test starts: its locks in a runtime directory
    of its own, so nothing another test or user holds can interfere (``run/cellctl``, named
    both ways cellctl looks for it)."""
    run = tmp_path / "run"
    run.mkdir(mode=0o700)
    own = {"XDG_RUNTIME_DIR": str(run), "CELLCTL_RUNTIME_DIR": str(run / "cellctl")}
    return {**os.environ, **own}


@dataclass
class Running:
    """A cellctl started by :func:`started`: its process and everything it printed so far."""

    proc: subprocess.Popen[str]
    output: list[str]
    reader: threading.Thread

    def printed(self) -> str:
        """All it printed, once it has exited (its output read to the end)."""
        self.reader.join(timeout=STOPPED_S)
        return "".join(self.output)


@contextmanager
def started(args: list[str], env: dict[str, str], ready: str) -> Iterator[Running]:
    """``cellctl ARGS`` in its own process, yielded once it prints a line matching ``ready``
    (within STARTED_S); stopped (SIGTERM, then SIGKILL) at the end, whatever happened."""
    proc = subprocess.Popen(
        [*CELLCTL, *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    output: list[str] = []
    lines: queue.Queue[str | None] = queue.Queue()

    def pump() -> None:
        assert proc.stdout is not None
        for row in proc.stdout:
            output.append(row)
            lines.put(row)
        lines.put(None)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        while True:
            try:
                row = lines.get(timeout=STARTED_S)
            except queue.Empty:
                pytest.fail(f"cellctl {' '.join(args)} did not start in time: {output}")
            if row is None:
                pytest.fail(f"cellctl {' '.join(args)} exited: {''.join(output)}")
            if re.search(ready, row):
                break
        yield Running(proc, output, reader)
    finally:
        stop(proc)


def stop(proc: subprocess.Popen[str]) -> None:
    """Stop ``proc`` as Ctrl-C would (SIGTERM); SIGKILL if it does not go in time."""
    if proc.poll() is None:
        proc.terminate()
    try:
        proc.wait(timeout=STOPPED_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=STOPPED_S)


def answers(link: Path, env: dict[str, str]) -> None:
    """A driver gets the robot's status at ``link``: the emulator serves there (and, its
    loop running, handles SIGTERM by closing cleanly)."""
    status = subprocess.run(
        [*CELLCTL, "robot", "--link", str(link), "status"],
        env=env,
        capture_output=True,
        text=True,
        timeout=REFUSED_S,
    )
    assert status.returncode == 0, status.stderr


def stopped_cleanly(robot: Running) -> None:
    """The emulator ran its close (which removes its link), not killed half-way."""
    assert robot.proc.returncode == 0, robot.printed()
    assert "emulator stopped" in robot.printed()


@contextmanager
def robot_at(path: Path, env: dict[str, str]) -> Iterator[Running]:
    """``cellctl emulate robot --listen pty:PATH``, up."""
    with started(["emulate", "robot", "--listen", f"pty:{path}"], env, r"--link ") as robot:
        yield robot


def refused(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """``cellctl ARGS`` run to its end (within REFUSED_S), its output captured."""
    return subprocess.run(
        [*CELLCTL, *args], env=env, capture_output=True, text=True, timeout=REFUSED_S
    )


def names(directory: Path) -> set[str]:
    """What is in ``directory`` (hidden names too: a temporary link left would show)."""
    return {p.name for p in directory.iterdir()}


# -- something that is not a link at PATH: refused, kept ---------------------------------------


def test_a_regular_file_at_path_is_refused_and_kept(tmp_path: Path, env: dict[str, str]) -> None:
    walk = tmp_path / "walk"
    walk.mkdir()
    plain = walk / "plainfile"
    plain.write_text("x\n")

    done = refused(["emulate", "robot", "--listen", f"pty:{plain}"], env)

    assert done.returncode == 2, done.stderr
    assert f"pty:{plain}: a regular file is there" in done.stderr
    assert "will not replace it: choose another path or remove it" in done.stderr
    assert "Traceback" not in done.stderr
    assert not plain.is_symlink()
    assert plain.read_text() == "x\n"
    assert names(walk) == {"plainfile"}


def test_a_directory_at_path_is_refused_and_nothing_is_left(
    tmp_path: Path, env: dict[str, str]
) -> None:
    walk = tmp_path / "walk"
    (walk / "d1").mkdir(parents=True)

    done = refused(["emulate", "robot", "--listen", f"pty:{walk / 'd1'}"], env)

    assert done.returncode == 2, done.stderr
    assert f"pty:{walk / 'd1'}: a directory is there" in done.stderr
    assert "Traceback" not in done.stderr
    assert names(walk) == {"d1"}
    assert names(walk / "d1") == set()


# -- one emulator per PATH ---------------------------------------------------------------------


def test_a_second_emulator_on_a_held_path_is_refused_naming_the_first(
    tmp_path: Path, env: dict[str, str]
) -> None:
    link = tmp_path / "robot.pty"
    with robot_at(link, env) as first:
        first_pty = os.readlink(link)

        done = refused(["emulate", "robot", "--listen", f"pty:{link}"], env)

        assert done.returncode == 6, done.stderr
        assert re.search(
            rf"pty:{re.escape(str(link))} is served by cellctl emulate robot "
            rf"\(pid {first.proc.pid}\) since \d\d:\d\d",
            done.stderr,
        ), done.stderr
        assert "Traceback" not in done.stderr
        # The first still answers at its documented path.
        assert os.readlink(link) == first_pty
        answers(link, env)
        assert first.proc.poll() is None
    stopped_cleanly(first)
    assert names(tmp_path) == {"run"}


def test_a_link_left_by_a_dead_emulator_is_replaced(tmp_path: Path, env: dict[str, str]) -> None:
    link = tmp_path / "robot.pty"
    with robot_at(link, env) as dead:
        dead_pty = os.readlink(link)
        dead.proc.kill()  # no cleanup: its link stays, pointing at a pty that is gone
        dead.proc.wait(timeout=STOPPED_S)
    assert os.readlink(link) == dead_pty
    left = os.lstat(link).st_ino

    with robot_at(link, env) as robot:
        assert robot.proc.poll() is None
        # A new link (the kernel may hand out the dead one's pty number again).
        assert os.lstat(link).st_ino != left
        assert Path(os.readlink(link)).exists()
        answers(link, env)
        assert names(tmp_path) == {"run", "robot.pty"}  # no temporary link left beside it
    # Its own link, so it goes on exit.
    stopped_cleanly(robot)
    assert names(tmp_path) == {"run"}


# -- on exit, PATH goes only if it is still the emulator's own ---------------------------------


@pytest.mark.parametrize("put_there", ["a file", "another link"])
def test_path_is_removed_on_exit_only_if_still_its_own(
    tmp_path: Path, env: dict[str, str], put_there: str
) -> None:
    link = tmp_path / "robot.pty"
    with robot_at(link, env) as robot:
        answers(link, env)
        # Something else takes PATH while the emulator runs (the user, another tool).
        tmp = tmp_path / "replacement"
        if put_there == "a file":
            tmp.write_text("mine\n")
        else:
            tmp.symlink_to(tmp_path / "elsewhere")
        os.replace(tmp, link)
    stopped_cleanly(robot)
    if put_there == "a file":
        assert not link.is_symlink()
        assert link.read_text() == "mine\n"
    else:
        assert os.readlink(link) == str(tmp_path / "elsewhere")


# -- emulate cell, twice on one directory ------------------------------------------------------


def test_emulate_cell_on_a_running_cell_is_refused_naming_it(
    tmp_path: Path, env: dict[str, str]
) -> None:
    cell = tmp_path / "cell"
    args = ["--cell", str(cell), "emulate", "cell"]
    with started(args, env, r"^\s*plc\s") as running:
        toml = (cell / "cell.toml").read_text()
        robot_pty = os.readlink(cell / "robot.pty")

        done = refused(args, env)

        assert done.returncode == 6, done.stderr
        assert "Traceback" not in done.stderr
        assert re.search(
            rf"robot\.pty is served by cellctl emulate cell \(pid {running.proc.pid}\)",
            done.stderr,
        ), done.stderr
        # The running cell is untouched: same cell.toml, same robot link.
        assert (cell / "cell.toml").read_text() == toml
        assert os.readlink(cell / "robot.pty") == robot_pty
        assert running.proc.poll() is None
        answers(cell / "robot.pty", env)


async def test_two_cells_started_at_once_in_one_directory_one_is_refused_before_it_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The robot's ``pty:PATH`` is taken before anything is written or served: of two starts
    at once, the one refused has written no file and started no machine (the check and the
    lock were two steps, and both starts passed the check)."""
    monkeypatch.setenv("CELLCTL_RUNTIME_DIR", str(tmp_path / "run"))
    cell = tmp_path / "cell"
    first, second = EmulatedCell(time_scale=1000.0), EmulatedCell(time_scale=1000.0)
    try:
        results = await asyncio.gather(
            first.start(cell), second.start(cell), return_exceptions=True
        )
        assert results[0] == cell / "cell.toml", results
        assert isinstance(results[1], MachineInUse), results
        assert "robot.pty is served by" in str(results[1])
        assert second.plc_url == "" and not second.servers  # nothing of it started
        assert first.plc_url in (cell / "cell.toml").read_text()
    finally:
        await second.close()
        await first.close()
    # Both gone: the path is free for the next start.
    again = EmulatedCell(time_scale=1000.0)
    try:
        assert await again.start(cell) == cell / "cell.toml"
    finally:
        await again.close()
