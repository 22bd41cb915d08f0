"""The console reads whole at 80x24 in a real terminal: tmux runs the installed ``cellctl
console`` on an emulated cell (its own process) with ``cellctl run`` in another, and the
test reads the screen as the operator does: the header once the controller stops (and the
traffic pane following the menu then), Ctrl-C, and WHAT IF's plans compared side by side.
"""

from __future__ import annotations

import os
import re
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellctl.plan.when import PLAN_POLL_S
from tests.test_console_tmux import (
    CELLCTL,
    Tmux,
    emulated_cell,
    stop,
    tmux_session,
    wait_until,
)

#: The terminal's columns.
WIDTH = 80


def settled(tmux: Tmux) -> str:
    """The screen once it holds still (the same on two looks 0.3 s apart)."""
    before = tmux.screen()
    for _ in range(100):
        time.sleep(0.3)
        now = tmux.screen()
        if now == before:
            return now
        before = now
    raise AssertionError(f"the screen does not hold still:\n{before}")


@pytest.fixture
def tmux() -> Iterator[Tmux]:
    yield from tmux_session()


def test_a_disconnected_console_in_a_terminal(tmux: Tmux, tmp_path: Path) -> None:
    """``cellctl run`` stops under an attached console: the header says so on its own line,
    whole; the traffic pane names the machine whose menu is open (not the robot's bytes it
    showed before); Ctrl-C quits, as ``q`` does."""
    cell = tmp_path / "cell"
    with emulated_cell(cell, controller=False):
        env = {**os.environ, "NO_COLOR": "1"}
        run = subprocess.Popen(
            [CELLCTL, "--cell", str(cell), "run", "--no-live"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
        )  # fmt: skip
        try:
            wait_until(lambda: (cell / "api.sock").exists(), "the controller's API socket")
            tmux.start([CELLCTL, "--cell", str(cell), "console"], {"TERM": "xterm-256color"})
            tmux.wait_for("MAIN MENU", "attached to cellctl run (pid")
            tmux.keys("1")
            tmux.wait_for("ROBOT (robot)", "7. EXIT")
            tmux.keys("4")
            tmux.wait_for("robot: STATUS: robot state", "traffic: robot (>> sent")
            wait_until(lambda: " <<  " in tmux.screen(), "the robot's bytes in the pane")
        finally:
            stop(run)
        shown = tmux.wait_for("DISCONNECTED")
        lines = shown.splitlines()
        header = "DISCONNECTED: controller's API closed; attaching again when it runs (q quits)"
        assert lines[0].strip() == header, shown
        assert lines[1].strip().startswith("cell: "), shown  # the directory on the next line
        tmux.keys("Escape")
        tmux.wait_for("MAIN MENU")
        tmux.keys("2")
        tmux.wait_for("NC MACHINE #1 (cnc1)", "6. EXIT")
        tmux.keys("4")
        shown = tmux.wait_for("cnc1: STATUS: the control API closed the connection")
        shown = tmux.wait_for("traffic: cnc1 (DISCONNECTED", "no traffic seen on cnc1")
        assert "traffic: robot" not in shown and " <<  " not in shown, shown
        tmux.keys("C-c")
        wait_until(tmux.pane_dead, "the console to quit on Ctrl-C")
        assert "ctrl+q" not in tmux.screen()


@pytest.mark.timeout(300)  # three plans play on a busy box: CPU, not waiting
def test_what_if_compares_policies_readable_at_80_columns(tmux: Tmux, tmp_path: Path) -> None:
    """Policy ``all``: each plan's header reads whole (it goes on under itself), every line
    of the view in the terminal's columns."""
    cell = tmp_path / "cell"
    with emulated_cell(cell, controller=True):
        tmux.start([CELLCTL, "--cell", str(cell), "console"], {"TERM": "xterm-256color"})
        tmux.wait_for("MAIN MENU", "attached to cellctl run (pid", "c. CELL")
        tmux.keys("c")
        tmux.wait_for("9. WHAT IF (plan ahead)")
        tmux.keys("9")
        tmux.wait_for("Horizon:", "Policy:", "Seed:")
        # Tab into a field selects its text: what is typed replaces it.
        tmux.focus_row("Horizon:")
        tmux.keys("-l", "2m")
        wait_until(lambda: re.search(r"Horizon:\s+2m ", tmux.screen()), "2m in the horizon")
        tmux.focus_row("Add orders:")
        tmux.keys("-l", "wax-robot-base:1")
        wait_until(lambda: re.search(r"Add orders:\s+wax-robot-base:1 ", tmux.screen()), "order")
        tmux.focus_row("Policy:")
        tmux.keys("-l", "all")
        wait_until(lambda: re.search(r"Policy:\s+all ", tmux.screen()), "all in the policy")
        assert re.search(r"Horizon:\s+2m ", tmux.screen()), tmux.screen()
        tmux.keys("Enter")
        tmux.wait_for("plan of CIM laboratory machining cell", timeout=240)
        # The whole view, page by page, to its Gantt charts (each plan's header is above).
        seen: list[str] = []
        for _ in range(20):
            shown = settled(tmux)  # a page scrolled to its end (the scroll is animated)
            # The text's columns, without the scroll bar's (the last).
            seen += [line[: WIDTH - 1].rstrip() for line in shown.splitlines()]
            if "Gantt chart, policy shortest-first" in shown:
                break
            tmux.keys("PageDown")
            wait_until(lambda before=shown: tmux.screen() != before, "the view to scroll", 10)
        text = "\n".join(seen)
        for policy in ("downstream-first", "one-at-a-time", "shortest-first"):
            # On its line, or going on under it (the longer policies' names).
            head = rf"cell \(policy {policy}, seed 0,( |\n\s+)poll {PLAN_POLL_S:g} s\)$"
            assert re.search(head, text, re.MULTILINE), text
        assert "policies compared:" in text, text
        # The longest lines, whole (78 columns): the chart's legend, the order table's head.
        assert (
            "one character = 2.0 s: A wax-robot-base, ! failed step, x fault window, . idle" in text
        )
        assert "order     part type           made finishes     due          verdict" in text
        tmux.keys("Enter")
        tmux.wait_for("9. WHAT IF")
        tmux.keys("q")
        wait_until(tmux.pane_dead, "the console to quit")
