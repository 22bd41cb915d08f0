"""The console's WHAT IF in a real terminal: tmux (80x24) runs the installed ``cellctl
console`` attached to ``cellctl run`` on an emulated cell (each in its own process); the plan
comes through the controller's API and its report and Gantt rows are read off the screen."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellctl.plan.when import PLAN_POLL_S
from cellctl.ui.console.whatif import GANTT_WIDTH
from tests.test_console_tmux import (
    CELLCTL,
    Tmux,
    emulated_cell,
    tmux_session,
    wait_until,
    wait_until_true,
)

GANTT_ROW = re.compile(rf"^\s*(robot|cnc1|cnc2)\s*\|([^|]{{{GANTT_WIDTH}}})\|", re.MULTILINE)


@pytest.fixture
def tmux() -> Iterator[Tmux]:
    yield from tmux_session()


@pytest.mark.timeout(300)  # the plan plays on a busy box: CPU, not waiting
def test_what_if_in_a_terminal(tmux: Tmux, tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    with emulated_cell(cell, controller=True):
        tmux.start([CELLCTL, "--cell", str(cell), "console"], {"TERM": "xterm-256color"})
        tmux.wait_for("MAIN MENU", "attached to cellctl run (pid", "c. CELL")
        tmux.keys("c")
        tmux.wait_for("8. EXIT", "9. WHAT IF (plan ahead)")
        tmux.keys("9")
        tmux.wait_for("Horizon:", "Add orders:", "PART:QTY[@PRIORITY][ by WHEN]")
        # The first field (8h offered) is focused as the dialog mounts; keys sent before that
        # are lost, so the field is cleared until it is seen empty. Backspace is a binding,
        # taken after the key went up through the dialog, while a letter goes into the field
        # at once: sent in one burst, "2m" would be typed before the backspaces took it away.
        cleared = lambda: re.search(r"Horizon:\s+█", tmux.screen())  # noqa: E731
        for _ in range(3):
            tmux.keys("BSpace", "BSpace", "BSpace", "BSpace")
            if wait_until_true(cleared, 15.0):
                break
        wait_until(cleared, "the horizon cleared")
        tmux.keys("-l", "2m")
        wait_until(lambda: re.search(r"Horizon:\s+2m ", tmux.screen()), "2m in the horizon")
        assert re.search(r"Horizon:\s+2m ", tmux.screen()), tmux.screen()
        tmux.focus_row("Add orders:")
        tmux.keys("-l", "wax-robot-base:1")
        wait_until(lambda: "wax-robot-base:1" in tmux.screen(), "the order typed", 30.0)
        assert re.search(r"Add orders:\s+wax-robot-base:1 ", tmux.screen()), tmux.screen()
        # The horizon typed is still there as the form is sent (a failure says which field).
        assert re.search(r"Horizon:\s+2m ", tmux.screen()), tmux.screen()
        tmux.keys("Enter")
        shown = tmux.wait_for("Gantt chart, policy downstream-first", "one character = 2.0 s",
                                  timeout=240)  # fmt: skip
        cell = "plan of CIM laboratory machining cell"
        # The header, broken after a comma to fit the terminal's 80 columns.
        header = f"{cell} (policy downstream-first, seed 0,"
        assert header in shown and f"poll {PLAN_POLL_S:g} s)" in shown, shown
        assert re.search(r"^\s*plan-add1\s+wax-robot-base\s+\d/1 ", shown, re.MULTILINE), shown
        rows = dict(GANTT_ROW.findall(shown))
        assert set(rows) == {"robot", "cnc1", "cnc2"}, shown
        assert "A" in rows["robot"], shown  # the part's first transfer, in the first 2 min
        tmux.keys("Enter")
        tmux.wait_for("plan (downstream-first): on time", "9. WHAT IF")
        tmux.keys("q")
        wait_until(tmux.pane_dead, "the console to quit")
