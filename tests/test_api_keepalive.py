"""The control API's listeners when they are full: a client needs no token to hold a kept-alive
connection, so a listener full of idle ones closes the one that waited longest to let a new
one in; one full of busy connections (WebSockets) still refuses, whatever token the newcomer
brings. And an unknown method's name is answered cut short. A standalone server on a copy of
the example cell, over real sockets."""

from __future__ import annotations

import asyncio
import json
import logging
from pathlib import Path

import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import InvalidStatus

from cellctl.cell.config import check_cell
from cellctl.service.client import RemoteCell
from cellctl.service.server import ApiLimits, api_limits
from cellctl.service.token import add_token
from tests.conftest import until
from tests.test_api_hardening import answer, call, serve
from tests.test_api_hardening import cell as cell  # the fixture: a copy of the example cell
from tests.test_api_limits import get, http

#: A deadline for one answer or close on loopback: a hang guard, not a timing figure.
WAIT_S = 20


def full_at(cell: Path, connections: int) -> ApiLimits:
    """The limits ``[api] max_connections = connections`` in the cell's cell.toml gives (a
    head deadline that never runs out here)."""
    with (cell / "cell.toml").open("a", encoding="utf-8") as f:
        f.write(
            f'\n[api]\nlisten = "127.0.0.1:7125"\nheader_timeout = 60\n'
            f"max_connections = {connections}\n"
        )
    config, problems = check_cell(cell)
    assert config is not None, problems
    return api_limits(config.api)


class Held:
    """A kept-alive connection that asks ``GET /api/status`` with ``token`` (none: answered
    401, and the connection stays open)."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer

    @classmethod
    async def open(cls, port: int, token: str | None = None) -> Held:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        held = cls(reader, writer)
        assert await held.ask(token) == 401
        return held

    async def ask(self, token: str | None = None) -> int:
        """One request on this connection; the answer's status (read whole)."""
        auth = f"Authorization: Bearer {token}\r\n" if token else ""
        self.writer.write(f"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n{auth}\r\n".encode())
        async with asyncio.timeout(WAIT_S):
            head = await self.reader.readuntil(b"\r\n\r\n")
            length = int(head.lower().split(b"content-length: ")[1].split(b"\r\n")[0])
            await self.reader.readexactly(length)
        assert b"connection: close" not in head.lower(), head  # kept alive
        return int(head.split(b" ", 2)[1])

    async def closed_by_server(self) -> bool:
        """True once the server closed it with nothing more said."""
        async with asyncio.timeout(WAIT_S):
            return await self.reader.read() == b""

    def close(self) -> None:
        self.writer.close()


async def test_idle_keep_alive_connections_make_room_for_a_real_client(
    cell: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="cellctl.service.limits")
    async with serve(cell, full_at(cell, 3)) as served:
        token = served.server.token
        held = [await Held.open(served.port) for _ in range(3)]  # no token: 401 each
        try:
            # The CLI's client gets its call answered: the connection idle longest made room.
            url = f"ws://127.0.0.1:{served.port}"
            async with await RemoteCell.connect(token=token, url=url) as client:
                assert (await client.call("server.info"))["mode"] == "standalone"
                assert await held[0].closed_by_server()
                # And so does a plain HTTP client, in place of the next one in line.
                status, body = await http(served.port, get("/server/info", "127.0.0.1", token))
                assert status == 200 and json.loads(body)["mode"] == "standalone"
                assert await held[1].closed_by_server()
                # The one that waited least was left alone: it is still kept alive.
                assert await held[2].ask() == 401
        finally:
            for one in held:
                one.close()
    said = [r.getMessage() for r in caplog.records]
    assert any(
        "closed an idle connection from ('127.0.0.1', " in line
        and "the listener was full ([api] max_connections" in line
        for line in said
    ), said


async def test_connections_trickling_their_bodies_make_room_too(cell: Path) -> None:
    async with serve(cell, full_at(cell, 3)) as served:
        # The handover page reads its body before any token is checked: three clients
        # without one each start a body they never finish (a head deadline of 60 s here).
        tricklers = []
        for _ in range(3):
            reader, writer = await asyncio.open_connection("127.0.0.1", served.port)
            writer.write(
                b"POST /dashboard/handover HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                b"Content-Type: application/json\r\nContent-Length: 1000\r\n\r\n"
                b'{"code": "abc", '
            )
            await writer.drain()
            tricklers.append(Held(reader, writer))
        try:
            listeners = served.server._server.listeners  # type: ignore[union-attr]
            await until(lambda: sum(lst.open for lst in listeners) == 3, "all three in", WAIT_S)
            status, body = await http(
                served.port, get("/server/info", "127.0.0.1", served.server.token)
            )
            assert status == 200 and json.loads(body)["mode"] == "standalone", body
            assert await tricklers[0].closed_by_server()
        finally:
            for one in tricklers:
                one.close()


async def wrong_token_handshake(port: int) -> InvalidStatus:
    """A WebSocket handshake with a token that is none of the cell's: how it was refused."""
    with pytest.raises(InvalidStatus) as refused:
        async with asyncio.timeout(WAIT_S):
            await connect(
                f"ws://127.0.0.1:{port}/websocket",
                additional_headers={"Authorization": "Bearer wrong-" + "x" * 40},
            )
    return refused.value


async def still_served(sessions: list[ClientConnection]) -> None:
    for rid, ws in enumerate(sessions):
        await ws.send(call(rid, "server.info"))
        assert (await answer(ws, rid))["result"]["mode"] == "standalone"


async def test_a_wrong_token_cannot_close_a_websocket_session(cell: Path) -> None:
    limits = full_at(cell, 3)
    # [api] leaves one token fewer sessions than connections: two tokens fill the listener.
    assert limits.sessions_per_token == 2
    second = add_token(cell, "line2", "operator")
    async with serve(cell, limits) as served:
        sessions = [await served.ws(), await served.ws(second)]
        held: list[Held] = []
        try:
            # The third connection is the wrong token's, and the next one's, and so on: each
            # newcomer closes the idle one before it, never a session. So does a handshake.
            for _ in range(4):
                held.append(await Held.open(served.port, "wrong-" + "x" * 40))
                if len(held) > 1:
                    assert await held[-2].closed_by_server()
            assert (await wrong_token_handshake(served.port)).response.status_code == 403
            assert await held[-1].closed_by_server()
            await still_served(sessions)
            # A session takes the last connection: now every one is busy, and the wrong
            # token's handshake is refused before it is read, with the reason.
            sessions.append(await served.ws())
            refused = await wrong_token_handshake(served.port)
            assert refused.response.status_code == 503
            assert b"3 connections are open on this listener" in refused.response.body
            assert b"every one is busy" in refused.response.body
            status, body = await http(
                served.port, get("/server/info", "127.0.0.1", served.server.token)
            )
            assert status == 503 and b"3 connections are open" in body, body
            await still_served(sessions)
        finally:
            for one in held:
                one.close()
            for ws in sessions:
                await ws.close()


async def test_a_long_unknown_method_is_named_short(cell: Path) -> None:
    method = "cell.stat" + "u" * 9_991
    async with serve(cell) as served, await served.ws() as ws:
        await ws.send(call(1, method))
        error = (await answer(ws, 1))["error"]
    assert error["code"] == -32601, error
    assert len(error["message"]) < 200, error["message"][:300]
    assert f"no method {method[:64]!r}… (cut from 10000 characters)" in error["message"]
