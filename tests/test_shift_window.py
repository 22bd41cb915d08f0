"""`cellctl report shift --from/--to`: both ends take the same forms (HH:MM or a date and
time), read as a shift lead means them (the last such time, not the next); a window that ends
before it begins is refused naming both ends.

The cell is the example cell's cell.toml with no journal yet: the window is what is checked
(the report's `start` and `end` in --json), on the real clock the command reads.
"""

from __future__ import annotations

import json
import shutil
import time
from datetime import datetime, timedelta
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from cellctl.ui.cli import main

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    shutil.copytree(ROOT / "examples" / "cell", directory)
    return directory


def _shift(cell: Path, *args: str) -> Result:
    return CliRunner().invoke(main, ["--cell", str(cell), "report", "shift", *args])


def _window(cell: Path, *args: str) -> tuple[datetime, datetime]:
    result = _shift(cell, "--json", *args)
    assert result.exit_code == 0, result.output
    found = json.loads(result.output)
    return datetime.fromtimestamp(found["start"]), datetime.fromtimestamp(found["end"])


def _last(hhmm: str, before: datetime) -> datetime:
    """The last local ``hhmm`` at or before ``before`` (what the test expects)."""
    hour, minute = map(int, hhmm.split(":"))
    moment = before.replace(hour=hour, minute=minute, second=0, microsecond=0)
    return moment if moment <= before else moment - timedelta(days=1)


def test_to_takes_hh_mm_as_from_does(cell: Path) -> None:
    now = datetime.fromtimestamp(time.time())
    # Two hours ago, to the minute: today's (or, just after midnight, yesterday's).
    to = (now - timedelta(hours=2)).strftime("%H:%M")
    start, end = _window(cell, "--to", to)
    assert end == _last(to, now)
    assert start < end  # the default: 8 h before --to, not before the journal's first step

    # The night shift: --from is the last 22:00 before --to's 06:00, across midnight.
    start, end = _window(cell, "--from", "22:00", "--to", "06:00")
    assert end == _last("06:00", now)
    assert start == end - timedelta(hours=8)

    # --from alone: the last such time before now, to now.
    since = (now - timedelta(hours=3)).strftime("%H:%M")
    start, end = _window(cell, "--from", since)
    assert start == _last(since, now)
    assert timedelta(hours=3) <= end - start < timedelta(hours=3, minutes=2)


def test_hh_mm_after_a_full_from_is_the_next_such_time(cell: Path) -> None:
    start, end = _window(cell, "--from", "2026-11-25T22:00", "--to", "06:00")
    assert (start, end) == (datetime(2026, 11, 25, 22, 0), datetime(2026, 11, 26, 6, 0))
    # The full form for both ends, as before.
    start, end = _window(cell, "--from", "2026-11-25T06:00", "--to", "2026-11-25T14:00")
    assert (start, end) == (datetime(2026, 11, 25, 6, 0), datetime(2026, 11, 25, 14, 0))


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (
            ["--from", "2026-11-25T10:00", "--to", "2026-11-25T09:00"],
            ["ends before it starts (from 2026-11-25 10:00 to 2026-11-25 09:00)", "--from before"],
        ),
        (["--from", "2099-01-01T06:00"], ["ends before it starts (from 2099-01-01 06:00 to now, "]),
        (["--to", "25:00"], ["--to", "'25:00'", "HH:MM", "2026-11-25T06:00"]),
        (["--from", "6pm"], ["--from", "'6pm'", "HH:MM"]),
    ],
)
def test_a_window_that_cannot_be_is_refused_in_words(
    cell: Path, args: list[str], words: list[str]
) -> None:
    result = _shift(cell, *args)
    assert result.exit_code == 2, result.output
    for word in words:
        assert word in result.output, result.output
