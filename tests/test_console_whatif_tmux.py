"""The console's WHAT IF in a real terminal: tmux (80x24) runs the installed ``cellctl
console`` attached to ``cellctl run`` on an emulated cell (each in its own process); the plan
comes through the controller's API and its report and Gantt rows are read off the screen."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellctl.ui.console.whatif import GANTT_WIDTH
from tests.test_console_tmux import CELLCTL, Tmux, stop, wait_until

GANTT_ROW = re.compile(rf"^\s*(robot|cnc1|cnc2)\s*\|([^|]{{{GANTT_WIDTH}}})\|", re.MULTILINE)


@pytest.fixture
def terminal() -> Iterator[Tmux]:
    found = shutil.which("tmux") or ("/usr/bin/tmux" if os.path.exists("/usr/bin/tmux") else None)
    if found is None:
        pytest.fail("tmux is not installed: the console's terminal test needs it (make test)")
    session = Tmux(found)
    try:
        yield session
    finally:
        session.kill()


@pytest.mark.timeout(300)  # the plan plays on a busy box: CPU, not waiting
def test_what_if_in_a_terminal(terminal: Tmux, tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    env = {**os.environ, "NO_COLOR": "1"}
    emulator = subprocess.Popen(
        [CELLCTL, "--cell", str(cell), "emulate", "cell", "--time-scale", "100"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
    )
    controller: subprocess.Popen[bytes] | None = None
    try:
        wait_until(lambda: (cell / "cell.toml").exists(), "the emulated cell's cell.toml")
        controller = subprocess.Popen(
            [CELLCTL, "--cell", str(cell), "run", "--no-live"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )
        wait_until(lambda: (cell / "api.sock").exists(), "the controller's API socket")
        terminal.start([CELLCTL, "--cell", str(cell), "console"], {"TERM": "xterm-256color"})
        terminal.wait_for("MAIN MENU", "attached to cellctl run (pid", "c. CELL")
        terminal.keys("c")
        terminal.wait_for("8. EXIT", "9. WHAT IF (plan ahead)")
        terminal.keys("9")
        terminal.wait_for("Horizon:", "Add orders:", "PART:QTY[@PRIORITY]")
        # The first field (focused, 8h offered) takes the keys once the dialog is up: on a
        # loaded box, keys sent before that are typed again.
        for _ in range(3):
            terminal.keys("BSpace", "BSpace", "BSpace", "BSpace")
            terminal.keys("-l", "2m")
            try:
                wait_until(lambda: re.search(r"Horizon:\s+2m ", terminal.screen()), "2m", 5.0)
                break
            except AssertionError:
                continue
        assert re.search(r"Horizon:\s+2m ", terminal.screen()), terminal.screen()
        terminal.focus_row("Add orders:")
        terminal.keys("-l", "wax-robot-base:1")
        terminal.keys("Enter")
        shown = terminal.wait_for("Gantt chart, policy default", "one character = 2.0 s",
                                  timeout=240)  # fmt: skip
        assert "plan of CIM laboratory machining cell (policy default, seed 0)" in shown
        assert re.search(r"^\s*plan-add1\s+wax-robot-base\s+\d/1 ", shown, re.MULTILINE), shown
        rows = dict(GANTT_ROW.findall(shown))
        assert set(rows) == {"robot", "cnc1", "cnc2"}, shown
        assert "A" in rows["robot"], shown  # the part's first transfer, in the first 2 min
        terminal.keys("Enter")
        terminal.wait_for("plan (default): on time", "9. WHAT IF")
        terminal.keys("q")
        wait_until(terminal.pane_dead, "the console to quit")
    finally:
        if controller is not None:
            stop(controller)
        stop(emulator)
