"""Orders' due times wherever orders are shown live: the status (``cell.status`` and the
subscription's pushes) from a running cell through the real control API, the console's board
and ORDERS list (Textual's Pilot, attached to a controller, and on virtual time as an order
passes its due time), OPC UA's ``Cell/Orders/<id>/Due`` and ``Late``, and a status from a
cellctl before due times, which has neither. The dashboard's: test_due_live_dashboard.py."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import time
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from asyncua.ua.uaerrors import UaError
from websockets.asyncio.client import ClientConnection, connect

from cellctl.cell.config import OpcuaTable
from cellctl.clock import current_clock
from cellctl.factory.opcua import NAMESPACE, OpcuaServer
from cellctl.service.access import AttachedCell
from cellctl.service.client import CellClient
from cellctl.service.status import CellStatus, StatusUpdate, apply_update_json
from cellctl.testing.rig import CellRig
from cellctl.ui.console.app import ConsoleApp
from cellctl.ui.console.widgets import board_text
from tests.conftest import free_port, until
from tests.test_api_hardening import answer, call
from tests.test_console import SIZE, attached, rig, standalone_client, wait_text
from tests.test_dashboard import dashboard_served
from tests.test_opcua import client_cert, session

__all__ = ["attached", "client_cert", "rig"]  # the fixtures, used by name

DAY = 86400.0
OPEN = ("posted", "accepted", "in-progress", "held")


def whole_minute(moment: datetime) -> datetime:
    return moment.replace(second=0, microsecond=0)


def shown(due: float) -> str:
    """A due time as the console and the dashboard show it: day, date, local 24-hour time."""
    return datetime.fromtimestamp(due).strftime("%a %m-%d %H:%M")


def backlog() -> tuple[str, float]:
    """A due time two hours past, as a planner types it (a date and time), and as unix s."""
    text = whole_minute(datetime.now() - timedelta(hours=2)).isoformat(timespec="minutes")
    return text, datetime.fromisoformat(text).timestamp()


def ahead() -> float:
    """A due time three days ahead, on a whole minute."""
    return whole_minute(datetime.now() + timedelta(days=3)).timestamp()


async def ask(ws: ClientConnection, rid: int, method: str, params: dict[str, Any]) -> Any:
    """The result of one call on ``ws`` (the pushes that came meanwhile are passed over)."""
    await ws.send(call(rid, method, params))
    reply = await answer(ws, rid)
    assert "result" in reply, reply
    return reply["result"]


def submit(oid: str, due: Any) -> dict[str, Any]:
    """``orders.submit``'s parameters for one wax-robot-base, due ``due`` (None: none)."""
    return {"part_type": "wax-robot-base", "id": oid, **({"due": due} if due is not None else {})}


def by_id(orders: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    return {o["id"]: o for o in orders}


def agrees(update: dict[str, Any]) -> None:
    """Each open order of a pushed ``update`` is late exactly when the status was built
    after its due time (the status' own time: one clock for both)."""
    for o in update.get("orders", []):
        if o["state"] in OPEN and o["due"] is not None:
            assert o["late"] == (update["time"] > o["due"]), (update["time"], o)


# -- through the control API ------------------------------------------------------------------


async def test_the_status_of_a_running_cell_carries_due_times_and_turns_late(
    tmp_path: Path,
) -> None:
    """A controller runs the cell, its API on loopback; a client sends orders due two hours
    ago, in three days and never: ``cell.status`` says when each is due and which is late;
    one due two seconds ahead is pushed late by the subscription as its time passes, with
    nothing else changing (the cell is paused: it stays as it was put)."""
    past_text, past = backlog()
    later = ahead()
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        async with dashboard_served(rig) as (server, base):
            url = base.replace("http://", "ws://") + "/websocket"
            headers = {"Authorization": f"Bearer {server.token}"}
            async with connect(url, additional_headers=headers, max_size=None) as ws:
                await ask(ws, 1, "cell.pause", {})
                for rid, (oid, due) in enumerate([("P1", past_text), ("A1", later), ("N1", None)]):
                    await ask(ws, 10 + rid, "orders.submit", submit(oid, due))
                status = await ask(ws, 20, "cell.status", {})
                orders = by_id(status["orders"])
                assert {k: (o["due"], o["late"]) for k, o in orders.items()} == {
                    "P1": (past, True),
                    "A1": (later, False),
                    "N1": (None, False),
                }
                held = await ask(ws, 21, "cell.subscribe", {})
                assert by_id(held["orders"])["P1"]["late"] is True
                soon = time.time() + 2.0
                await ws.send(call(22, "orders.submit", submit("S1", soon)))
                seen: list[Any] = []
                await answer(ws, 22, seen)
                pushes = 0

                def take(message: Any) -> None:
                    nonlocal held, pushes
                    if isinstance(message, dict) and message.get("method") == (
                        "notify_status_update"
                    ):
                        update = message["params"]
                        StatusUpdate.model_validate(update)  # the pushed fields, typed
                        agrees(update)
                        held = apply_update_json(held, update)
                        pushes += 1

                for message in seen:
                    take(message)
                async with asyncio.timeout(30):  # the due time is 2 s ahead; a push a second
                    while not by_id(held["orders"]).get("S1", {}).get("late"):
                        take(json.loads(await ws.recv()))
    s1 = by_id(held["orders"])["S1"]
    assert (s1["due"], s1["state"]) == (soon, "accepted")
    assert by_id(held["orders"])["A1"]["late"] is False
    assert pushes >= 1
    CellStatus.model_validate(held)  # what a subscriber holds is a whole status


# -- a status from before due times -----------------------------------------------------------

OLD_ORDER = {
    "id": "OLD1",
    "part_type": "wax-robot-base",
    "qty": 2,
    "priority": 0,
    "state": "in-progress",
    "created": 1_700_000_000.0,
    "updated": 1_700_000_100.0,
    "note": "",
    "parts": {"active": 1, "waiting": 1},
    "blocked": "",
}
OLD_STATUS = {
    "cell": {
        "name": "lab",
        "directory": "/cells/lab",
        "access": "attached",
        "mode": "running",
        "paused": False,
        "started_at": 1_700_000_000.0,
        "pid": 4242,
        "time": 1_700_000_200.0,
    },
    "machines": {},
    "orders": [OLD_ORDER],
    "parts": [],
    "alarms": [],
    "events": [],
}


def test_a_status_from_a_cellctl_before_due_times_is_read_as_none_due() -> None:
    """A controller of an older cellctl sends orders without ``due`` and ``late`` (in
    ``cell.status`` and in its pushes): a client reads each as due never, not late, and
    shows it as it did."""
    status = CellStatus.model_validate_json(json.dumps(OLD_STATUS))
    [order] = status.orders
    assert (order.due, order.late) == (None, False)
    update = StatusUpdate.model_validate_json(
        json.dumps({"time": 1_700_000_300.0, "orders": [{**OLD_ORDER, "state": "done"}]})
    )
    assert update.orders is not None and update.orders[0].due is None
    held = apply_update_json(OLD_STATUS, update.as_json())
    assert CellStatus.model_validate(held).orders[0].state == "done"
    board = board_text(OLD_STATUS, 60).plain
    assert " OLD1 wax-robot-base x2 p0 in-progress 0/2" in board and "due" not in board


# -- the console ------------------------------------------------------------------------------


async def test_the_console_shows_due_times_and_late(rig: CellRig, attached: CellClient) -> None:
    """Attached to a running controller at 80x24: the board shows each order's due time and
    LATE for the one past it; CELL -> ORDERS lists the same."""
    past_text, past = backlog()
    later = ahead()
    await attached.call("cell.pause", {})
    await attached.call("orders.submit", submit("P1", past_text))
    await attached.call("orders.submit", submit("A1", later))
    await attached.call("orders.submit", submit("N1", None))
    app = ConsoleApp(rig.directory, attached, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "attached to cellctl run")
        board = await wait_text(pilot, "ORDERS 3 open", f"due {shown(past)} LATE")
        # At 80 columns an order's due time has a line of its own, under the order's.
        assert under(board, "P1 wax-robot-base x1") == f"due {shown(past)} LATE"
        assert under(board, "A1 wax-robot-base x1") == f"due {shown(later)}"
        assert "due" not in under(board, "N1 wax-robot-base x1")
        await pilot.press("c")
        await wait_text(pilot, "1. ORDERS")
        await pilot.press("1")
        listed = await wait_text(pilot, "ORDERS (live)", f"due {shown(later)}")
        rows = {o: line_of(listed, f"{o} wax-robot-base x1 p0") for o in ("P1", "A1", "N1")}
        assert f"due {shown(past)} LATE" in rows["P1"], rows
        assert f"due {shown(later)}" in rows["A1"] and "LATE" not in rows["A1"], rows
        assert "due" not in rows["N1"] and "LATE" not in rows["N1"], rows
        await pilot.press("escape", "escape", "q")


def line_of(screen: str, text: str) -> str:
    """The screen's line that holds ``text``."""
    return next(line for line in screen.splitlines() if text in line)


def under(screen: str, text: str) -> str:
    """The board's line under the one that holds ``text``, its words only."""
    lines = screen.splitlines()
    at = next(i for i, line in enumerate(lines) if text in line)
    return lines[at + 1].split("│")[-1].strip()


@pytest.mark.virtual
async def test_the_boards_order_turns_late_at_its_due_time(rig: CellRig) -> None:
    """On virtual time (no load can make it late): an order due a whole minute ahead on the
    cell's clock is shown due, not late; once the clock passes its due time, LATE, with
    nothing else changing."""
    clock = current_clock()
    due = (math.floor(clock.now() / 60) + 2) * 60.0
    rig.mailbox.post_order("wax-robot-base", 1, order_id="S1", due=due)
    app = ConsoleApp(rig.directory, standalone_client(rig), traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        first = await wait_text(pilot, f"due {shown(due)}")
        assert clock.now() < due and f"due {shown(due)} LATE" not in first
        await wait_text(pilot, f"due {shown(due)} LATE", timeout=600)
        assert clock.now() > due
        await pilot.press("q")


# -- OPC UA -----------------------------------------------------------------------------------


async def test_opcua_shows_each_orders_due_time_and_late(
    tmp_path: Path, client_cert: tuple[str, str]
) -> None:
    """``Cell/Orders/<id>/Due`` (DateTime; OPC UA's null DateTime for none) and ``Late``,
    read by an anonymous reader of a running cell's server."""
    past_text, past = backlog()
    later = ahead()
    url = f"opc.tcp://127.0.0.1:{free_port()}"
    async with CellRig(tmp_path / "cell") as rig:
        controller = await rig.start_controller()
        server = OpcuaServer(AttachedCell(controller), OpcuaTable(listen=url, anonymous_read=True))
        await server.dispatcher.call("cell.pause", {})
        for oid, due in [("P1", past_text), ("A1", later), ("N1", None)]:
            await server.dispatcher.call("orders.submit", submit(oid, due))
        await server.start()
        try:
            async with session(url, rig.directory, client_cert) as reader:
                idx = await reader.get_namespace_index(NAMESPACE)

                async def value(oid: str, name: str) -> Any:
                    node = reader.get_node(ua.NodeId(f"Cell/Orders/{oid}/{name}", idx))
                    with contextlib.suppress(UaError):
                        return await node.read_value()
                    return None

                async def every_order_shown() -> bool:
                    return all([await value(o, "Late") is not None for o in ("P1", "A1", "N1")])

                await until(every_order_shown, "the orders' nodes", timeout=30)
                assert (await value("P1", "Due")).timestamp() == past
                assert await value("P1", "Late") is True
                assert (await value("A1", "Due")).timestamp() == later
                assert await value("A1", "Late") is False
                assert (await value("N1", "Due")).year == 1601  # OPC UA's null DateTime
        finally:
            await server.close()
