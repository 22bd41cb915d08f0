"""The issue's "can we take 40 more robot bases by Friday?": ``cellctl plan --add
'PART:QTY[@PRIORITY] by WHEN'`` adds an order due at WHEN (as ``--until`` and ``cellctl
submit --due`` write it, from the plan's start), and the plan's line for it says on time or
late as for any order with a due time. Each case is built from the plan's own report (when it
says the order finishes), played by ``cellctl plan`` in its own process: from a cell
directory, and from a cell's files through ``plan.run`` (the running cell's way). A form it
cannot read is refused with the form, before anything plays."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.errors import UsageError
from cellctl.plan.spec import AddSpec, parse_add
from cellctl.plan.when import resolve_when

from .conftest import CELLCTL

#: The plans start on a Wednesday at 06:00 local time.
START = "2026-11-25T06:00"
T0 = datetime(2026, 11, 25, 6, 0).timestamp()
BASE = "wax-robot-base"


def iso(stamp: float) -> str:
    """A local date and time to the second, as a planner may type it."""
    return datetime.fromtimestamp(stamp).isoformat(timespec="seconds")


def cellctl(*args: str, expect: int = 0) -> subprocess.CompletedProcess[str]:
    """``cellctl ARGS`` in a process of its own."""
    done = subprocess.run(
        [*CELLCTL, *args], capture_output=True, text=True, timeout=240, check=False
    )
    assert done.returncode == expect, done.stdout + done.stderr
    return done


def orders_of(done: subprocess.CompletedProcess[str]) -> dict[str, dict[str, Any]]:
    """The plan's orders (``--json``), by id."""
    plans = json.loads(done.stdout)["plans"]
    assert len(plans) == 1
    return {o["order_id"]: o for o in plans[0]["orders"]}


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("plan-add-due") / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    return directory


# -- the form ------------------------------------------------------------------------------------


def test_by_reads_the_times_until_and_due_take_from_the_plans_start() -> None:
    assert parse_add(f"{BASE}:40@5 by FRI 18:00", T0) == AddSpec(
        BASE, 40, 5, datetime(2026, 11, 27, 18, 0).timestamp()
    )
    assert parse_add(f"{BASE}:40 BY 18:00", T0).due == resolve_when("18:00", T0)
    assert parse_add(f"  {BASE} : 40 by  2026-12-04T18:00 ", T0).due == (
        datetime(2026, 12, 4, 18, 0).timestamp()
    )
    # Past already (the backlog as it is): taken, late from the start.
    assert parse_add(f"{BASE}:1 by 2026-11-20T12:00", T0).due == (
        datetime(2026, 11, 20, 12, 0).timestamp()
    )
    # Without a due time, as it always was.
    assert parse_add(f"{BASE}:40@5", T0) == AddSpec(BASE, 40, 5)


FORM = "write PART:QTY[@PRIORITY][ by WHEN], e.g."
WITH_DUE = "(an order with a due time: PART:QTY[@PRIORITY] by WHEN, e.g."


@pytest.mark.parametrize(
    ("text", "words"),
    [
        (f"{BASE}:40 by", FORM),
        (f"{BASE}:40 due FRI 18:00", FORM),
        (f"{BASE}:40@5by FRI 18:00", FORM),
        (f"{BASE}:40 by FRI 18:00 " + "x" * 60, FORM),
        (f"{BASE}:40 by Friday", "due time 'Friday': write HH:MM, DAY HH:MM (FRI 18:00)"),
        (f"{BASE}:40 by 25:00", "due time '25:00': hours 0-23, minutes 0-59"),
        (f"{BASE}:40 by FRY 18:00", "'FRY' is not a day"),
        (f"{BASE}:40 by 9999-01-01T00:00", "an order's due time must be unix seconds"),
    ],
)
def test_a_malformed_due_is_refused_with_the_form(text: str, words: str) -> None:
    with pytest.raises(UsageError) as refused:
        parse_add(text, T0)
    said = str(refused.value)
    assert said.startswith(f"--add {text!r}: ") and words in said, said
    assert FORM in said or WITH_DUE in said, said


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=70))
@example("18:00\n")
@example("2026-13-01T00:00")
def test_anything_after_by_is_read_or_refused_in_words(when: str) -> None:
    try:
        added = parse_add(f"{BASE}:2 by {when}", T0)
    except UsageError as e:
        assert str(e).startswith("--add ")
        return
    assert added.due is not None and added.qty == 2


# -- the plan's verdict --------------------------------------------------------------------------


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_an_added_order_says_on_time_or_late_against_its_due_time(cell: Path) -> None:
    """Due when the plan ends, the order is done by then: on time, and the plan says when it
    finishes. The same plan with the order due a minute before that: late by that minute."""
    plan = ["plan", "--dir", str(cell), "--start", START, "--shift", "1h"]
    due = T0 + 3600
    first = orders_of(cellctl(*plan, "--add", f"{BASE}:1 by WED 07:00", "--json"))
    (order,) = first.values()
    assert (order["due"], order["verdict"], order["late_s"]) == (due, "on time", 0.0), order
    finished = order["finished"]
    assert finished is not None and T0 < finished <= due, order
    early = math.floor(finished) - 60
    text = cellctl(*plan, "--add", f"{BASE}:1 by {iso(early)}").stdout
    (line,) = [row for row in text.splitlines() if row.startswith("plan-add1 ")]
    when = datetime.fromtimestamp(early).strftime("%a %H:%M:%S")
    finishes = datetime.fromtimestamp(round(finished)).strftime("%a %H:%M:%S")
    words = line.split()
    assert words[3:7] == [*finishes.split(), *when.split()], text
    # A minute, and the part of a second the finish has past a whole one (rounded up).
    assert words[7:] in (["late", "by", "0:01:00"], ["late", "by", "0:01:01"]), text
    assert "on time 0, late 1" in text, text


@pytest.mark.timeout(300)
def test_plan_run_of_a_cells_files_takes_the_added_due_times(tmp_path: Path) -> None:
    """``cellctl plan`` of a cell no controller runs calls ``plan.run`` on its files, as the
    running cell's service does: one order due a day after the plan starts, done within it,
    is on time; one due a day before it started is late from the start."""
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    now = datetime.now().replace(microsecond=0, second=0)
    ahead, behind = now + timedelta(days=1), now - timedelta(days=1)
    done = cellctl(
        "--cell", str(cell), "plan", "--shift", "3h", "--json",
        "--add", f"{BASE}:1 by {ahead.isoformat()}",
        "--add", f"wax-toy-mill-table:1@5 by {behind.isoformat()}",
    )  # fmt: skip
    found = orders_of(done)
    assert {k: (o["due"], o["verdict"]) for k, o in found.items()} == {
        "plan-add1": (ahead.timestamp(), "on time"),
        "plan-add2": (behind.timestamp(), "late"),
    }, found
    assert found["plan-add2"]["priority"] == 5
    # A plan writes nothing into the cell it plans.
    assert sorted(os.listdir(cell)) == sorted(os.listdir(EXAMPLE_CELL))


def test_a_malformed_add_is_refused_before_anything_plays(cell: Path) -> None:
    """As a planner runs it (its own process): one line, exit 2, no plan."""
    done = cellctl(
        "plan", "--dir", str(cell), "--start", START,
        "--add", f"{BASE}:40 due FRI 18:00", expect=2,
    )  # fmt: skip
    assert done.stderr.strip().splitlines() == [
        f"error: --add '{BASE}:40 due FRI 18:00': write PART:QTY[@PRIORITY][ by WHEN], e.g. "
        f"{BASE}:40, {BASE}:40@5 or {BASE}:40@5 by FRI 18:00"
    ]
    assert done.stdout == ""
