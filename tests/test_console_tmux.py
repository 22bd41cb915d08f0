"""``cellctl console`` in a real terminal: tmux (80x24) runs the installed binary against an
emulated cell in its own process and a controller (``cellctl run``) in another; the test
reads the screen as an operator would.

A missing tmux fails the test with a clear message (``make test`` installs it).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

CELLCTL = str(Path(sys.executable).parent / "cellctl")
DEADLINE = 30.0


def wait_until(condition: object, what: str, timeout: float = DEADLINE) -> None:
    """Poll ``condition()`` until true; fail naming ``what`` after ``timeout`` seconds."""
    assert callable(condition)
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def wait_until_true(condition: Callable[[], object], timeout: float) -> bool:
    """Whether ``condition`` holds within ``timeout`` seconds (polled)."""
    try:
        wait_until(condition, "", timeout)
    except AssertionError:
        return False
    return True


class Tmux:
    """A tmux server of its own (``-L``), one detached 80x24 session."""

    def __init__(self, tmux: str) -> None:
        self.tmux = tmux
        self.socket = f"cellctl-console-{uuid.uuid4().hex[:12]}"
        self.session = "console"

    def run(self, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [self.tmux, "-L", self.socket, *args],
            capture_output=True,
            text=True,
            check=check,
            timeout=10,
        )

    def start(
        self, command: list[str], env: dict[str, str], width: int = 80, height: int = 24
    ) -> None:
        self.run(
            "new-session", "-d", "-s", self.session, "-x", str(width), "-y", str(height),
            *[f"-e{k}={v}" for k, v in env.items()],
            " ".join(command),
        )  # fmt: skip
        self.run("set-option", "-t", self.session, "remain-on-exit", "on")

    def screen(self) -> str:
        result = self.run("capture-pane", "-p", "-t", self.session, check=False)
        return result.stdout

    def wait_for(self, *texts: str, timeout: float = DEADLINE) -> str:
        deadline = time.monotonic() + timeout
        while True:
            shown = self.screen()
            if all(t in shown for t in texts):
                return shown
            if time.monotonic() > deadline:
                raise AssertionError(f"not on the terminal: {texts}\n{shown}")
            time.sleep(0.1)

    def keys(self, *keys: str) -> None:
        self.run("send-keys", "-t", self.session, *keys)

    def cursor_row(self) -> int:
        """The terminal's cursor row (a focused input puts the cursor in its field)."""
        result = self.run("display-message", "-p", "-t", self.session, "#{cursor_y}", check=False)
        return int(result.stdout.strip() or -1)

    def on_row(self, text: str) -> bool:
        """Whether the cursor is on the row that shows ``text``, on a screen that held still
        while the cursor was read (a dialog that grows or shrinks moves its rows)."""
        before = self.screen()
        row = self.cursor_row()
        lines = before.splitlines()
        return self.screen() == before and 0 <= row < len(lines) and text in lines[row]

    def focus_row(self, text: str) -> None:
        """Tab until the cursor is on the row that shows ``text`` (a field's label; called
        from another field). One Tab at a time, each taken before the next (the cursor
        moved): a Tab sent again because the application was slow may overshoot, and Tab
        goes round, so it comes back."""
        for _ in range(12):
            row = self.cursor_row()
            self.keys("Tab")
            try:
                wait_until(lambda r=row: self.cursor_row() != r, f"a Tab towards {text}", 5.0)
            except AssertionError:
                continue
            if wait_until_true(lambda: self.on_row(text), 0.5):
                return
        raise AssertionError(f"Tab did not reach {text}:\n{self.screen()}")

    def pane_dead(self) -> bool:
        result = self.run("display-message", "-p", "-t", self.session, "#{pane_dead}", check=False)
        return result.stdout.strip() == "1"

    def kill(self) -> None:
        self.run("kill-server", check=False)


@pytest.fixture
def tmux() -> Iterator[Tmux]:
    yield from tmux_session()


def tmux_session() -> Iterator[Tmux]:
    """A tmux server of its own for one test, killed after it (the ``tmux`` fixture)."""
    found = shutil.which("tmux") or ("/usr/bin/tmux" if os.path.exists("/usr/bin/tmux") else None)
    if found is None:
        pytest.fail("tmux is not installed: the console's terminal test needs it (make test)")
    session = Tmux(found)
    try:
        yield session
    finally:
        session.kill()


def stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)


@contextlib.contextmanager
def emulated_cell(cell: Path, *, controller: bool) -> Iterator[None]:
    """``cellctl emulate cell`` (time scale 100) writing ``cell``, and ``cellctl run`` on it
    if ``controller`` (its API socket up): processes, stopped on the way out."""
    env = {**os.environ, "NO_COLOR": "1"}
    quiet: dict[str, Any] = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "env": env}
    emulate = [CELLCTL, "--cell", str(cell), "emulate", "cell", "--time-scale", "100"]
    procs = [subprocess.Popen(emulate, **quiet)]
    try:
        wait_until(lambda: (cell / "cell.toml").exists(), "the emulated cell's cell.toml")
        if controller:
            run = [CELLCTL, "--cell", str(cell), "run", "--no-live"]
            procs.append(subprocess.Popen(run, **quiet))
            wait_until(lambda: (cell / "api.sock").exists(), "the controller's API socket")
        yield
    finally:
        for proc in reversed(procs):
            stop(proc)


def test_console_in_a_terminal_attached_to_a_running_cell(tmux: Tmux, tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    with emulated_cell(cell, controller=True):
        tmux.start([CELLCTL, "--cell", str(cell), "console"], {"TERM": "xterm-256color"})
        # The source's main menu: 1 ROBOT, 2 NC #1, 3 NC #2, 4 EXIT; the cell on a letter.
        shown = tmux.wait_for("MAIN MENU", "attached to cellctl run (pid", "4. EXIT", "c. CELL")
        assert "1. ROBOT (robot)" in shown and "3. NC MACHINE #2 (cnc2)" in shown
        menu = [line[:36].strip() for line in shown.splitlines()[2:14]]  # the menu column
        assert [m for m in menu if m] == [
            "1. ROBOT (robot)", "2. NC MACHINE #1 (cnc1)", "3. NC MACHINE #2 (cnc2)", "4. EXIT",
            "c. CELL (orders, parts, alarms)",
        ], shown  # fmt: skip
        tmux.keys("1")
        tmux.wait_for("ROBOT (robot)", "7. EXIT", "s. OUT OF SERVICE")
        tmux.keys("4")  # STATUS: an observation, allowed in automatic service
        tmux.wait_for("robot: STATUS: robot state", "partitions: 1 ")
        tmux.wait_for("traffic: robot", ">> ", "<< ")  # the robot's traffic, both ways
        tmux.keys("Escape")
        tmux.wait_for("MAIN MENU")
        tmux.keys("q")
        wait_until(tmux.pane_dead, "the console to quit")


def test_console_in_a_terminal_a_refused_value_is_replaced_by_what_is_typed_next(
    tmux: Tmux, tmp_path: Path
) -> None:
    """Standalone (no controller): the robot's DOWNLOAD refuses partition 6; what the
    operator types next replaces the field's text ("4", not "64"), and the .aml source the
    picker offers is compiled on the way."""
    cell = tmp_path / "cell"
    with emulated_cell(cell, controller=False):
        tmux.start([CELLCTL, "--cell", str(cell), "console"], {"TERM": "xterm-256color"})
        tmux.wait_for("MAIN MENU", "standalone: links held by this console", "4. EXIT")
        tmux.keys("1")
        tmux.wait_for("ROBOT (robot)", "7. EXIT")
        tmux.keys("1")
        tmux.wait_for("robot: INITIALIZE: Initializing was correct")
        tmux.keys("2")
        tmux.wait_for("Partition (1-5):", "robot")  # the picker shows the robot/ folder
        tmux.keys("6")
        tmux.wait_for("Partition (1-5):      6")
        tmux.focus_row("Program file:")
        tmux.keys("-l", "robot/cnc1_to_cnc2.aml")
        tmux.wait_for("Program file:         robot/cnc1_to_cnc2.aml")
        tmux.keys("Enter")
        tmux.wait_for("partition must be 1 to 5, not 6")
        tmux.keys("4")  # replaces the refused 6 (the cursor was in the program field)
        tmux.wait_for("Partition (1-5):      4 ")
        tmux.keys("Enter")
        tmux.wait_for("robot: DOWNLOAD: Download was correct")
        tmux.keys("4")
        tmux.wait_for("robot: STATUS: robot state", "4 Full (CNC1TOCN)")
        tmux.keys("q")
        wait_until(tmux.pane_dead, "the console to quit")


def cellctl(cell: Path, *args: str) -> str:
    """A ``cellctl`` command on ``cell``; its output (it must succeed)."""
    done = subprocess.run(
        [CELLCTL, "--cell", str(cell), *args], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def event_rows(screen: str) -> int:
    """The rows of the live view's events pane (each starts with its HH:MM:SS)."""
    return len(re.findall(r"^│ \d\d:\d\d:\d\d ", screen, re.MULTILINE))


def test_run_live_view_in_a_terminal(tmux: Tmux, tmp_path: Path) -> None:
    """``cellctl run``'s live view: a header (cell, time scale, how to stop), a PAUSED and
    an EMERGENCY STOP banner, a machine's out-of-service reason, and an events pane that
    grows with the terminal."""
    cell = tmp_path / "cell"
    with emulated_cell(cell, controller=False):
        # The terminal's size, not one the environment fixes (COLUMNS, LINES).
        command = ["env", "-u", "COLUMNS", "-u", "LINES", CELLCTL, "--cell", str(cell), "run"]
        tmux.start(command, {"TERM": "xterm-256color"}, 100, 30)
        tmux.wait_for("cellctl run: cell", "time scale 100 (emulated cell)", "Ctrl-C stops")
        wait_until(lambda: (cell / "api.sock").exists(), "the controller's API socket")
        cellctl(cell, "pause")
        tmux.wait_for("PAUSED: no new step starts")
        cellctl(cell, "machine", "cnc2", "out", "--reason", "noise")
        tmux.wait_for("│ cnc2 ", "OUT: taken out", "noise")
        cellctl(cell, "machine", "cnc1", "out", "--reason", "tool change")
        for _ in range(4):  # fifteen events by now: more than a 30-row terminal shows
            cellctl(cell, "resume")
            cellctl(cell, "pause")
        # 30 rows: the events pane has the rows the rest leaves.
        shown = tmux.wait_for("paused by token:default (engineer)", "cellctl run: cell")
        small = event_rows(shown)
        assert small >= 1, shown
        # A taller terminal: the events pane takes the room.
        tmux.run("resize-window", "-t", tmux.session, "-x", "100", "-y", "60")
        grown = lambda: event_rows(tmux.screen()) > max(small, 6)  # noqa: E731
        try:
            wait_until(grown, "more events on a taller screen")
        except AssertionError:
            raise AssertionError(f"no more events on a taller screen:\n{tmux.screen()}") from None
        cellctl(cell, "estop", "smoke at cnc1")
        tmux.wait_for("EMERGENCY STOP: smoke at cnc1. Deal with its cause", "cellctl resume")
        tmux.keys("C-c")
        wait_until(tmux.pane_dead, "cellctl run to stop on Ctrl-C")
