"""A long plan says how far it has played while it plays: on a terminal (stderr a tty) a
line of machine time played of the plan's span, cleared before the plan is printed; in a
pipe, or with --json, nothing more than the plan. Shown or not, the plan is the same."""

from __future__ import annotations

import io
import json
import os
import pty
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from cellctl.clock import RealClock
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.ui.plan_progress import ProgressLine

PLAN = ["--add", "wax-robot-base:3", "--start", "2026-11-25T06:00", "--shift", "2h"]


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("plan-progress") / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    return directory


def on_a_terminal(*args: str) -> tuple[int, str, str]:
    """``cellctl ARGS`` with its stderr on a pty: exit code, stdout, what the pty showed."""
    main, other = pty.openpty()
    shown = bytearray()

    def read() -> None:
        while True:
            try:
                data = os.read(main, 4096)
            except OSError:  # the other end closed
                return
            if not data:
                return
            shown.extend(data)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        done = subprocess.run(
            [sys.executable, "-m", "cellctl", *args],
            stdout=subprocess.PIPE,
            stderr=other,
            text=True,
            timeout=240,
            check=False,
        )
    finally:
        os.close(other)
        reader.join(10)
        os.close(main)
    return done.returncode, done.stdout, shown.decode(errors="replace")


def same(text: str) -> list[str]:
    """A plan's text but for the real seconds it took to play."""
    return [re.sub(r" in [\d.]+ s$", "", line) for line in text.splitlines()]


@pytest.mark.timeout(600)  # plays on a busy box: CPU, not waiting
def test_a_plan_on_a_terminal_says_how_far_it_has_played(cell: Path) -> None:
    code, out, shown = on_a_terminal("plan", "--dir", str(cell), *PLAN)
    assert code == 0, shown
    assert "playing: " in shown and "of 2:00:00 machine time (" in shown, shown
    assert shown.endswith("\r\x1b[K"), repr(shown[-80:])  # cleared before the plan prints
    assert "plan of CIM laboratory machining cell" in out and "playing" not in out
    # Several policies, each in a process of its own: each one's share.
    code, out, shown = on_a_terminal("plan", "--dir", str(cell), *PLAN, "--policy", "all")
    assert code == 0, shown
    assert "playing 2:00:00 of machine time: " in shown and "one-at-a-time " in shown, shown
    # In a pipe: nothing on stderr, and the same plan as when progress was shown (but for
    # the real seconds it took).
    piped = subprocess.run(
        [sys.executable, "-m", "cellctl", "plan", "--dir", str(cell), *PLAN, "--policy", "all"],
        capture_output=True, text=True, timeout=240, check=False,
    )  # fmt: skip
    assert piped.returncode == 0 and piped.stderr == "", piped.stderr
    assert same(piped.stdout) == same(out)
    # With --json on a terminal: nothing but the plan.
    code, out, shown = on_a_terminal("plan", "--dir", str(cell), *PLAN, "--json")
    assert code == 0 and shown == "", shown
    assert json.loads(out)["plans"][0]["steps"]


@pytest.mark.timeout(600)
def test_a_plan_through_the_cells_api_says_how_far_it_has_played(cell: Path) -> None:
    """A cell no controller runs: ``plan.run`` on its files, played in a worker process
    whose progress comes back through the API's progress."""
    code, out, shown = on_a_terminal(
        "--cell", str(cell), "plan", "--add", "wax-robot-base:3", "--shift", "2h"
    )
    assert code == 0, shown
    assert "playing: " in shown and "of 2:00:00 machine time (" in shown, shown
    assert "plan of CIM laboratory machining cell" in out


class SetClock(RealClock):
    """The computer's time as the test sets it."""

    def __init__(self) -> None:
        super().__init__()
        self.at = 1000.0

    def monotonic(self) -> float:
        return self.at


def test_a_long_plan_says_how_long_the_rest_takes() -> None:
    """A month's plan takes minutes: once there is a pace to go by, the line says how long
    the rest takes at it (at most: the plan ends sooner when every order is done)."""
    clock, stream = SetClock(), io.StringIO()
    line = ProgressLine(stream, clock)
    told = line.told(31 * 86400.0)
    told("default", 600.0)  # at once: no pace yet
    assert line.text() == "playing: 0:10:00 of 31 d 0:00:00 machine time (0%)"
    clock.at += 30.0
    told("default", 8 * 3600.0)  # 8 h of plan in 30 s: the other 30 d 16 h in 46 min
    assert line.text() == (
        "playing: 8:00:00 of 31 d 0:00:00 machine time (1%, up to about 0:46:00 more)"
    )
    clock.at += 30.0 * 92 - 10.0
    told("default", 31 * 86400.0 - 600.0)
    assert line.text().endswith("(100%, under a minute more)")
    # Several policies side by side: all that is left of each, at their pace together.
    line = ProgressLine(io.StringIO(), clock)
    told = line.told(8 * 3600.0)
    clock.at += 60.0  # 4 h of plan in a minute: 12 h left in 3 minutes
    told("one-at-a-time", 2 * 3600.0)
    told("downstream-first", 2 * 3600.0)
    assert line.text() == (
        "playing 8:00:00 of machine time: one-at-a-time 25%, downstream-first 25% "
        "(up to about 0:03:00 more)"
    )
