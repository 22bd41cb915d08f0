"""A fault window's times as a planner types them: a wall time the clocks skip (the spring
forward) is the next that exists, not a day later; a time before the plan's start is the
next day's, and a refusal says how it read each time; a window may be given with a date."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from cellctl.emulators.cell import EXAMPLE_CELL


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("plan-when") / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    return directory


def cellctl(*args: str, tz: str = "Europe/Berlin") -> subprocess.CompletedProcess[str]:
    """``cellctl ARGS`` in a process of its own, in time zone ``tz``."""
    return subprocess.run(
        [sys.executable, "-m", "cellctl", *args],
        env=os.environ | {"TZ": tz},
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )


def local(text: str, tz: str = "Europe/Berlin") -> float:
    """The unix time of the local ``text`` (an existing wall time) in ``tz``."""
    from datetime import datetime
    from zoneinfo import ZoneInfo

    return datetime.fromisoformat(text).replace(tzinfo=ZoneInfo(tz)).timestamp()


def windows(cell: Path, *faults: str, start: str, shift: str = "1h") -> list[dict[str, Any]]:
    args = ["plan", "--dir", str(cell), "--add", "wax-robot-base:1", "--start", start]
    for fault in faults:
        args += ["--fault", fault]
    done = cellctl(*args, "--shift", shift, "--json")
    assert done.returncode == 0, done.stderr
    found: list[dict[str, Any]] = json.loads(done.stdout)["inputs"]["faults"]
    return found


@pytest.mark.timeout(600)  # plays on a busy box: CPU, not waiting
def test_a_time_the_clocks_skip_is_the_next_that_exists(cell: Path) -> None:
    """Europe/Berlin, 2027-03-28: the clocks go from 02:00 to 03:00."""
    found = windows(cell, "cnc1:down@02:30-03:30", "cnc2:down@01:30-02:30",
                    start="2027-03-28T01:00", shift="3h")  # fmt: skip
    # Not 03:30 to the next day's 03:30: 02:30 is no time that day, 03:00 is the next.
    assert (found[0]["start"], found[0]["end"]) == (
        local("2027-03-28T03:00"),
        local("2027-03-28T03:30"),
    )
    assert (found[1]["start"], found[1]["end"]) == (
        local("2027-03-28T01:30"),
        local("2027-03-28T03:00"),
    )
    # 02:00-03:00 is no time at all that day: refused as an end written as the start is.
    done = cellctl("plan", "--dir", str(cell), "--add", "wax-robot-base:1",
                   "--start", "2027-03-28T01:00", "--fault", "cnc1:down@02:00-03:00")  # fmt: skip
    said = " ".join(done.stderr.split())
    assert done.returncode == 2 and "the window ends as it opens" in said, said
    assert (
        "02:00 read as Sun 2027-03-28 03:00:00 (no 02:00 that day: the clocks go forward)" in said
    )


def test_a_refused_window_says_how_it_read_each_time(cell: Path) -> None:
    done = cellctl("plan", "--dir", str(cell), "--add", "wax-robot-base:1",
                   "--start", "2026-11-30T06:00", "--fault", "cnc1:down@05:00-06:30")  # fmt: skip
    said = " ".join(done.stderr.split())
    assert done.returncode == 2, said
    assert (
        "the window opens after the plan ends (Mon 2026-11-30 14:00:00): 05:00 read as Tue "
        "2026-12-01 05:00:00, 06:30 as Tue 2026-12-01 06:30:00, the next such time at or after "
        "the plan's start (Mon 2026-11-30 06:00:00)"
    ) in said


@pytest.mark.timeout(600)
def test_a_window_may_be_given_with_a_date(cell: Path) -> None:
    [found] = windows(cell, "cnc1:down@2026-11-30T06:30-2026-11-30T06:45", start="2026-11-30T06:00")
    assert (found["start"], found["end"]) == (
        local("2026-11-30T06:30"),
        local("2026-11-30T06:45"),
    )
