"""The control API against what a security tester threw at it: a flood of frames on one
session (and on one token's sessions), request bodies that trickle in, a stop while a
manual download runs, and a viewer filling the audit trail. Real servers over real sockets:
standalone on a copy of the example cell, or attached to the emulated cell."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import shutil
import signal
import sqlite3
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect

from cellctl.cell.journal import JOURNAL_FILE, open_journal
from cellctl.service.access import AttachedCell, LocalCell
from cellctl.service.audit import AuditLog
from cellctl.service.rpc import SERVER_BUSY
from cellctl.service.server import ApiLimits, ApiServer
from cellctl.service.token import add_token
from cellctl.testing.rig import CellRig
from cellctl.ui.dashboard.routes import dashboard_routes
from tests.conftest import free_port

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell"
#: A mill program of three blocks (the driver's tests stream it block by block).
LONG = EXAMPLE.parent / "programs" / "toy_mill_table_finish_cnc2.dyn"


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    shutil.copytree(EXAMPLE, directory)
    open_journal(directory).close()
    return directory


class Served:
    """A standalone server on TCP, and clients for it."""

    def __init__(self, server: ApiServer, port: int) -> None:
        self.server = server
        self.port = port

    async def ws(self, token: str | None = None) -> ClientConnection:
        headers = {"Authorization": f"Bearer {token or self.server.token}"}
        return await connect(
            f"ws://127.0.0.1:{self.port}/websocket", additional_headers=headers, max_size=None
        )


@contextlib.asynccontextmanager
async def serve(cell: Path, limits: ApiLimits | None = None) -> AsyncIterator[Served]:
    port = free_port()
    async with LocalCell(cell, {}) as access:
        server = ApiServer(
            access,
            cell,
            listen=f"127.0.0.1:{port}",
            extra_routes=dashboard_routes,
            limits=limits or ApiLimits(),
        )
        await server.start()
        try:
            yield Served(server, port)
        finally:
            await server.close()


def call(rid: int | str | None, method: str, params: dict[str, Any] | None = None) -> str:
    request: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "params": params or {}}
    if rid is not None:
        request["id"] = rid
    return json.dumps(request)


async def answer(ws: ClientConnection, rid: Any, seen: list[Any] | None = None) -> Any:
    """The answer to request ``rid`` (progress notifications and other answers go to
    ``seen``, in the order they came)."""
    async with asyncio.timeout(120):
        while True:
            message = json.loads(await ws.recv())
            if isinstance(message, dict) and message.get("id") == rid:
                return message
            if seen is not None:
                seen.append(message)


def busy(message: Any, reason: str) -> bool:
    error: Any = message.get("error") if isinstance(message, dict) else None
    return bool(error) and error["code"] == SERVER_BUSY and error["data"]["reason"] == reason


# -- finding 1: calls in flight per session and per token ---------------------------------------


async def test_a_call_past_the_sessions_cap_is_refused_at_once_then_served(cell: Path) -> None:
    async with serve(cell, ApiLimits(calls_per_session=1)) as served, await served.ws() as ws:
        plan_run = {"shift": "1h", "add": ["wax-robot-base:2"]}  # seconds in a worker process
        await ws.send(call(1, "plan.run", plan_run))
        await ws.send(call(2, "server.info"))
        await ws.send(json.dumps([json.loads(call(3, "server.info")), {"jsonrpc": "2.0"}]))
        seen: list[Any] = []
        plan = await answer(ws, 1, seen)
        assert "plan" in plan["result"], plan
        # Refused while the plan was in flight, at once (before the plan's answer), with why.
        # (The plan's progress notifications come meanwhile too: not answers.)
        refused, batch = [m for m in seen if not (isinstance(m, dict) and "method" in m)]
        assert busy(refused, "connection") and refused["id"] == 2
        assert "this connection has 1 call in flight" in refused["error"]["message"]
        assert refused["error"]["data"]["limit"] == 1
        assert isinstance(batch, list) and [a["id"] for a in batch] == [3]
        assert busy(batch[0], "connection")
        # The slot is free again.
        await ws.send(call(4, "server.info"))
        assert (await answer(ws, 4))["result"]["mode"] == "standalone"


async def test_one_tokens_calls_in_flight_are_capped_over_its_sessions(cell: Path) -> None:
    viewer = add_token(cell, "vera", "viewer")
    limits = ApiLimits(calls_per_session=4, calls_per_token=1)
    async with serve(cell, limits) as served:
        a, b, other = await served.ws(viewer), await served.ws(viewer), await served.ws()
        try:
            await a.send(call(1, "plan.run", {"shift": "1h", "add": ["wax-robot-base:2"]}))
            await a.send(call(2, "server.info"))
            seen: list[Any] = []
            first = await answer(a, 2, seen)
            assert busy(first, "token") and "the token 'vera' has 1 call" in str(first)
            # Another session of the same token: refused too; another token's: served.
            await b.send(call(3, "server.info"))
            assert busy(await answer(b, 3), "token")
            await other.send(call(4, "server.info"))
            assert (await answer(other, 4))["result"]["mode"] == "standalone"
            assert "plan" in (await answer(a, 1))["result"]
            await b.send(call(5, "server.info"))
            assert (await answer(b, 5))["result"]["mode"] == "standalone"
        finally:
            for ws in (a, b, other):
                await ws.close()


async def test_a_flood_of_frames_is_refused_past_the_cap_and_others_are_served(
    cell: Path,
) -> None:
    viewer = add_token(cell, "vera", "viewer")
    count = 3000
    async with serve(cell) as served:
        flood, other = await served.ws(viewer), await served.ws()
        answers: dict[int, Any] = {}

        async def take() -> None:  # the flooding client reads its answers as they come
            async with asyncio.timeout(120):
                while len(answers) < count:
                    message = json.loads(await flood.recv())
                    answers[message["id"]] = message

        taking = asyncio.create_task(take())
        try:
            for i in range(count):  # each a read in a worker thread: they pile up in flight
                await flood.send(call(i, "audit.list"))
            await other.send(call("mine", "server.info"))
            assert (await answer(other, "mine"))["result"]["mode"] == "standalone"
            await taking
        finally:
            taking.cancel()
            await flood.close()
            await other.close()
    assert sorted(answers) == list(range(count))  # every frame answered, once
    refused = [m for m in answers.values() if "error" in m]
    assert refused, "no call of the flood was refused: nothing caps the calls in flight"
    assert all(busy(m, "connection") for m in refused), refused[:3]
    assert any("result" in m for m in answers.values())


# -- finding 2: request bodies that never end ----------------------------------------------------


async def drip(writer: asyncio.StreamWriter) -> None:
    """A body's bytes, one every 0.2 s, until the connection is closed under it."""
    with contextlib.suppress(ConnectionError):
        while not writer.is_closing():
            writer.write(b"x")
            await writer.drain()
            await asyncio.sleep(0.2)


async def trickle(port: int, head: bytes) -> tuple[asyncio.StreamReader, asyncio.Task[None]]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(head)
    return reader, asyncio.create_task(drip(writer))


async def until_closed(reader: asyncio.StreamReader) -> bytes:
    """What came until the server closed the connection (its end of the stream, or the
    next byte dripped into a closed socket)."""
    data = b""
    async with asyncio.timeout(30):  # the deadline under test is 1 s: this bounds the test only
        with contextlib.suppress(ConnectionError):
            while chunk := await reader.read(65536):
                data += chunk
    return data


HUGE_GET = b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 100000000\r\n\r\n"


async def test_a_body_that_trickles_in_is_cut_off_at_its_deadline(cell: Path) -> None:
    async with serve(cell, ApiLimits(header_timeout=1.0)) as served:
        # No token: answered 401 at once, and closed once the body's deadline passed.
        reader, dripping = await trickle(served.port, HUGE_GET)
        data = await until_closed(reader)
        dripping.cancel()
        assert data.startswith(b"HTTP/1.1 401") and data.count(b"HTTP/1.1") == 1, data
        # With the token, to a call that reads its body: 408 with the reason, and closed.
        head = (
            b"POST /dashboard/call HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            + f"Authorization: Bearer {served.server.token}\r\n".encode()
            + b"Content-Type: application/json\r\nContent-Length: 5000\r\n\r\n{"
        )
        reader, dripping = await trickle(served.port, head)
        data = await until_closed(reader)
        dripping.cancel()
        assert data.startswith(b"HTTP/1.1 408"), data
        assert b"the request's body did not come within 1 s" in data


async def test_trickling_bodies_do_not_hold_the_listeners_connections(cell: Path) -> None:
    async with serve(cell, ApiLimits(header_timeout=1.0, max_connections=3)) as served:
        held = [await trickle(served.port, HUGE_GET) for _ in range(3)]
        try:
            for reader, _ in held:  # each answered 401: each holds one of the 3 connections
                async with asyncio.timeout(30):
                    assert (await reader.readuntil(b"\r\n")).startswith(b"HTTP/1.1 401")
            request = (
                b"GET /server/info HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                + f"Authorization: Bearer {served.server.token}\r\n".encode()
                + b"Connection: close\r\n\r\n"
            )
            statuses: list[bytes] = []
            async with asyncio.timeout(30):  # until the trickling ones are closed: 503 before
                while not statuses or statuses[-1] != b"200":
                    reader, writer = await asyncio.open_connection("127.0.0.1", served.port)
                    writer.write(request)
                    statuses.append((await reader.read()).split(b" ", 2)[1])
                    writer.close()
                    await asyncio.sleep(0.05)
            assert set(statuses) <= {b"503", b"200"}, statuses
            for reader, _ in held:  # the server closed each, its body still coming
                await until_closed(reader)  # (else: TimeoutError)
        finally:
            for _, dripping in held:
                dripping.cancel()


# -- finding 3: stopping while a manual download runs --------------------------------------------


class Stalled:
    """The emulated cell, its controller and API; a download by hand on cnc2 held after
    its first block (the mill's READY does not come back until the operator selects its
    link mode again), with a deadline far beyond the test's."""

    def __init__(self, rig: CellRig, server: ApiServer, ws: ClientConnection) -> None:
        self.rig = rig
        self.server = server
        self.ws = ws

    def said(self, text: str) -> bool:
        controller = self.rig.controller
        return controller is not None and any(text in e.text for e in controller.events)

    async def closing(self) -> asyncio.Task[None]:
        """``server.close()`` begun, and waiting for the download (it says so)."""
        task = asyncio.create_task(self.server.close())
        await self.rig.wait_for(
            lambda: self.said("waiting for the API calls in flight to end: mill.download"),
            "closing waiting for the download",
        )
        return task


@pytest.fixture
async def stalled(tmp_path: Path) -> AsyncIterator[Stalled]:
    async with CellRig(tmp_path / "cell", mill_options={"block_extra": 600.0}) as rig:
        controller = await rig.start_controller()
        port = free_port()
        server = ApiServer(AttachedCell(controller), rig.directory, listen=f"127.0.0.1:{port}")
        await server.start()
        headers = {"Authorization": f"Bearer {server.token}"}
        ws = await connect(f"ws://127.0.0.1:{port}/websocket", additional_headers=headers)
        try:
            await ws.send(call(1, "machines.out_of_service", {"machine": "cnc2"}))
            assert "result" in await answer(ws, 1)
            await rig.wait_for(lambda: not controller.steps_in_flight(), "no step in flight")
            async with asyncio.timeout(60):  # its setup done (NEXT pressed): state 2, ready
                for asked in itertools.count(100):
                    await ws.send(call(asked, "mill.status", {"machine": "cnc2"}))
                    if (await answer(ws, asked))["result"]["state"] == 2:
                        break
                    await asyncio.sleep(0.1)
            rig.switch_on("cnc2:stall")
            params = {"machine": "cnc2", "program": LONG.name, "text": LONG.read_text()}
            await ws.send(call(2, "mill.download", params))
            mill = rig.cell.mills["cnc2"]
            await rig.wait_for(lambda: mill.onsets.get("stall"), "block 1 cut, READY held low")
            yield Stalled(rig, server, ws)
        finally:
            await ws.close()
            await server.close()


def audited(cell: Path, method: str) -> list[str]:
    with AuditLog(cell) as log:
        return [e.result for e in log.entries() if e.method == method]


async def test_closing_waits_for_a_download_in_flight_to_end(stalled: Stalled) -> None:
    closing = await stalled.closing()
    # Meanwhile a new call is refused: the API stops.
    await stalled.ws.send(call(3, "cell.status"))
    assert busy(await answer(stalled.ws, 3), "stopping")
    assert not closing.done()
    # The operator selects the link mode: READY, and the download goes on to its end.
    await stalled.rig.switch_off("cnc2:stall")
    progress: list[Any] = []
    done = await answer(stalled.ws, 2, progress)
    assert done["result"]["message"] == "Download was correct", done
    assert {p["params"]["block"] for p in progress if p.get("method") == "notify_progress"} >= {3}
    async with asyncio.timeout(60):
        await closing  # once the download's answer went out
    mill = stalled.rig.cell.mills["cnc2"]
    assert [r.outcome for r in mill.runs if r.lines_executed > 100][-3:] == ["block end"] * 3
    assert audited(stalled.rig.directory, "mill.download") == ["ok"]


async def test_an_acting_call_cut_short_is_said_and_audited_cancelled(
    stalled: Stalled, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    closing = await stalled.closing()
    closing.cancel()  # as asyncio.run's Ctrl-C handler cancels `cellctl run`'s main task
    with pytest.raises(asyncio.CancelledError):
        await closing
    assert stalled.said("mill.download by token:default on cnc2: cut short before its end")
    assert "mill.download by token:default was cut short" in caplog.text
    assert audited(stalled.rig.directory, "mill.download") == ["cancelled"]


async def test_a_sigterm_while_closing_waits_cuts_the_calls_short(stalled: Stalled) -> None:
    before = signal.getsignal(signal.SIGTERM)
    assert before is signal.SIG_DFL  # nobody handles it here: closing takes it, as in `cellctl run`
    closing = await stalled.closing()
    # Closing handles SIGTERM while it waits (else this test would end pytest).
    assert signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL
    signal.raise_signal(signal.SIGTERM)
    async with asyncio.timeout(60):
        await closing  # it goes on closing, the download cut short
    assert stalled.said("mill.download by token:default on cnc2: cut short before its end")
    assert audited(stalled.rig.directory, "mill.download") == ["cancelled"]
    assert signal.getsignal(signal.SIGTERM) is before


# -- finding 4: the audit trail is bounded ------------------------------------------------------


async def test_a_flood_of_refusals_is_one_counted_entry_and_what_was_done_stays(
    cell: Path,
) -> None:
    viewer = add_token(cell, "vera", "viewer")
    operator = add_token(cell, "olga", "operator")
    reason = "r" * 480
    async with serve(cell) as served:
        async with await served.ws(operator) as ws:
            await ws.send(call(1, "orders.submit", {"part_type": "wax-robot-base", "id": "A1"}))
            assert "result" in await answer(ws, 1)
        async with await served.ws(viewer) as ws:
            for batch in range(10):  # 1,000 refused emergency stops, in batches of 100
                calls = [{"jsonrpc": "2.0", "id": batch * 100 + i, "method": "cell.estop",
                          "params": {"reason": reason}} for i in range(100)]  # fmt: skip
                await ws.send(json.dumps(calls))
                refused = json.loads(await ws.recv())
                assert all(a["error"]["data"]["role"] == "operator" for a in refused)
    with AuditLog(cell) as log:
        entries = log.entries(limit=10_000)
    stops = [e for e in entries if e.method == "cell.estop"]
    assert len(stops) == 1 and stops[0].who == "token:vera" and stops[0].repeats == 1000
    assert "needs the operator role (and 999 times more in the next" in stops[0].result
    assert [e.result for e in entries if e.method == "orders.submit"] == ["ok"]


def test_the_audit_trail_keeps_the_newest_of_each_outcome(tmp_path: Path) -> None:
    open_journal(tmp_path).close()
    with AuditLog(tmp_path) as log:
        for i in range(20):
            log.record("token:olga", "orders.submit", {"id": f"A{i}"}, "ok")
            log.record(f"token:v{i}", "cell.estop", {}, "vera is a viewer: ...")
    # The next log (a restart) prunes at its first entry: 5 successes, 3 others kept.
    with AuditLog(tmp_path, keep_ok=5, keep_other=3) as log:
        log.record("token:olga", "orders.submit", {"id": "A20"}, "ok")
        entries = log.entries(limit=1000)
    done = [json.loads(e.params)["id"] for e in entries if e.result == "ok"]
    assert done == ["A16", "A17", "A18", "A19", "A20"]
    assert [e.who for e in entries if e.result != "ok"] == ["token:v17", "token:v18", "token:v19"]


def test_a_journal_from_before_gains_the_counted_columns(tmp_path: Path) -> None:
    with sqlite3.connect(tmp_path / JOURNAL_FILE) as db:
        db.execute(
            "CREATE TABLE audit (id INTEGER PRIMARY KEY AUTOINCREMENT, at REAL NOT NULL, "
            "who TEXT NOT NULL, method TEXT NOT NULL, params TEXT NOT NULL, result TEXT NOT NULL)"
        )
        db.execute(
            "INSERT INTO audit (at, who, method, params, result) "
            "VALUES (1.0, 'token:ann', 'cell.pause', '{}', 'ok')"
        )
    db.close()
    with AuditLog(tmp_path) as log:
        for _ in range(3):
            log.record("token:vera", "cell.pause", {}, "vera is a viewer: no", collapse=True)
        entries = log.entries()
    assert [(e.who, e.repeats) for e in entries] == [("token:ann", 1), ("token:vera", 3)]
