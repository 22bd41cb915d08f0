"""An order's due time through the control API and into a plan of the running cell: the real
server on loopback (``orders.submit``'s ``due`` as unix seconds or as ``--until`` text,
``orders.list``'s ``due`` and ``late``), ``plan.run`` and ``cellctl plan`` (no ``--dir``)
saying on time or late per order, each plan played on virtual time."""

from __future__ import annotations

import json
import os
import subprocess
import time
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection

from cellctl.mailbox import MAILBOX_FILE, open_mailbox
from cellctl.service.rpc import INVALID_PARAMS
from tests.conftest import CELLCTL
from tests.test_api_hardening import answer, call, serve
from tests.test_api_hardening import cell as cell  # the fixture: a copy of the example cell

DAY = 86400.0


async def ask(ws: ClientConnection, rid: int, method: str, params: dict[str, Any]) -> Any:
    """The answer (``result`` or ``error``) to one call on ``ws``."""
    await ws.send(call(rid, method, params))
    return await answer(ws, rid)


async def submit(ws: ClientConnection, rid: int, oid: str, due: Any) -> Any:
    """``orders.submit`` of one wax-robot-base, order ``oid``, due ``due`` (None: none)."""
    params: dict[str, Any] = {"part_type": "wax-robot-base", "id": oid}
    if due is not None:
        params["due"] = due
    return await ask(ws, rid, "orders.submit", params)


def minute(moment: datetime) -> str:
    """``moment`` as a date and time to the minute, as a planner types it."""
    return moment.replace(second=0, microsecond=0).isoformat(timespec="minutes")


async def test_orders_submit_takes_a_due_time_as_unix_seconds_or_as_text(cell: Path) -> None:
    ahead = time.time() + 3 * DAY
    past = datetime.now() - timedelta(hours=2)
    async with serve(cell) as served:
        ws = await served.ws()
        try:
            posted = await submit(ws, 1, "S", ahead)
            friday = await submit(ws, 2, "T", "FRI 18:00")
            behind = await submit(ws, 3, "P", minute(past))
            refused = [
                await submit(ws, 10 + n, f"X{n}", due)
                for n, due in enumerate(["friday", True, [1], "9" * 100, -5, 1e300])
            ]
            listed = await ask(ws, 20, "orders.list", {})
        finally:
            await ws.close()
    order = posted["result"]["order"]
    assert (order["id"], order["due"], order["late"]) == ("S", ahead, False)
    due_friday = datetime.fromtimestamp(friday["result"]["order"]["due"])
    assert (due_friday.weekday(), due_friday.hour, due_friday.minute) == (4, 18, 0)
    assert behind["result"]["message"].endswith("(already past: the order is late)")
    # Each refusal in words, naming the parameter; none of them posted.
    words = [r["error"]["message"] for r in refused]
    assert all(r["error"]["code"] == INVALID_PARAMS for r in refused)
    assert words[0].startswith("orders.submit: due: time 'friday': write HH:MM, DAY HH:MM")
    assert "due: a due time is unix seconds or text (FRI 18:00), not true or false" in words[1]
    assert "not a list" in words[2] and "at most 60 characters" in words[3]
    assert all("due time must be unix seconds from 0 to" in w for w in words[4:]), words
    entries = {o["id"]: o for o in listed["result"]}
    assert set(entries) == {"S", "T", "P"}
    assert (entries["P"]["due"], entries["P"]["late"]) == (
        datetime.fromisoformat(minute(past)).timestamp(),
        True,
    )
    assert entries["S"]["late"] is False and entries["T"]["late"] is False


def verdicts(plan: dict[str, Any]) -> dict[str, tuple[Any, str]]:
    """Per order of the plan's only policy: its due time and its verdict."""
    [report] = plan["plans"]
    return {o["order_id"]: (o["due"], o["verdict"]) for o in report["orders"]}


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
async def test_a_plan_of_the_cell_says_on_time_or_late_per_order(cell: Path) -> None:
    """``plan.run`` on the real server: the cell's open orders are played with their due
    times, as a plan of an orders file is: one already overdue is late, one due in a week is
    on time, one with none just finishes."""
    overdue = minute(datetime.now() - timedelta(hours=1))
    week = time.time() + 7 * DAY
    async with serve(cell) as served:
        ws = await served.ws()
        try:
            for rid, (oid, due) in enumerate([("LATE", overdue), ("WEEK", week), ("ANY", None)]):
                assert "result" in await submit(ws, rid, oid, due)
            planned = await ask(ws, 9, "plan.run", {"shift": "3h"})
        finally:
            await ws.close()
    plan = planned["result"]["plan"]
    expected_due = {
        "LATE": datetime.fromisoformat(overdue).timestamp(),
        "WEEK": week,
        "ANY": None,
    }
    assert {o["order_id"]: o["due"] for o in plan["inputs"]["orders"]} == expected_due
    assert verdicts(plan) == {
        "LATE": (expected_due["LATE"], "late"),
        "WEEK": (week, "on time"),
        "ANY": (None, "finished"),
    }
    [report] = plan["plans"]
    late = next(o for o in report["orders"] if o["order_id"] == "LATE")
    assert late["late_s"] >= 3600 - 60  # finished after the plan's start: an hour and more


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_cellctl_plan_of_the_cell_reads_the_due_times_submit_gave(cell: Path) -> None:
    """``cellctl submit --due``, then ``cellctl plan`` (no ``--dir``, no controller: the same
    ``plan.run`` in the command's own process, on copies of the cell's files)."""

    def cellctl(*args: str) -> str:
        done = subprocess.run(
            [*CELLCTL, "--cell", str(cell), *args],
            capture_output=True,
            text=True,
            timeout=240,
            env={**os.environ, "COLUMNS": "200"},
        )
        assert done.returncode == 0, (done.stdout, done.stderr)
        return done.stdout

    overdue = minute(datetime.now() - timedelta(days=1))
    later = minute(datetime.now() + timedelta(days=20))
    cellctl("submit", "wax-robot-base", "--id", "BACKLOG", "--due", overdue)
    cellctl("submit", "wax-toy-mill-table", "--id", "LATER", "--due", later)
    before = (cell / MAILBOX_FILE).read_bytes()
    plan = json.loads(cellctl("plan", "--shift", "4h", "--json"))
    assert verdicts(plan) == {
        "BACKLOG": (datetime.fromisoformat(overdue).timestamp(), "late"),
        "LATER": (datetime.fromisoformat(later).timestamp(), "on time"),
    }
    text = cellctl("plan", "--shift", "4h")
    rows = {line.split()[0]: line for line in text.splitlines() if line[:1].isupper()}
    assert "late by " in rows["BACKLOG"] and rows["LATER"].endswith("on time")
    # The plan read copies: the cell's mailbox is as submit left it.
    assert (cell / MAILBOX_FILE).read_bytes() == before
    with open_mailbox(cell) as mailbox:
        assert sorted(mailbox.due_times()) == ["BACKLOG", "LATER"]
