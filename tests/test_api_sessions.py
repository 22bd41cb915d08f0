"""One token cannot take every connection of the API: a viewer opening WebSockets is refused
past ``[api] sessions_per_token`` (429, in words), and an operator still reaches the cell.
A real server, standalone on a copy of the example cell, over real sockets."""

from __future__ import annotations

import asyncio
import json
import shutil
from pathlib import Path

import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import InvalidStatus

from cellctl.cell.config import check_cell
from cellctl.cell.journal import open_journal
from cellctl.service.server import ApiLimits, api_limits
from cellctl.service.token import add_token
from tests.test_api_hardening import EXAMPLE, answer, call, serve


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    shutil.copytree(EXAMPLE, directory)
    open_journal(directory).close()
    return directory


async def refused(port: int, token: str) -> InvalidStatus:
    with pytest.raises(InvalidStatus) as caught:
        async with connect(
            f"ws://127.0.0.1:{port}/websocket",
            additional_headers={"Authorization": f"Bearer {token}"},
        ):
            pass
    return caught.value


async def test_one_token_cannot_take_every_connection(cell: Path) -> None:
    viewer = add_token(cell, "vera", "viewer")
    operator = add_token(cell, "olga", "operator")
    limits = ApiLimits(max_connections=6, sessions_per_token=3)
    async with serve(cell, limits) as served:
        held: list[ClientConnection] = []
        try:
            for _ in range(3):
                held.append(await served.ws(viewer))
            # The viewer's 4th (and every other it tries, up to every slot) is refused.
            for _ in range(3):
                refusal = await refused(served.port, viewer)
                assert refusal.response.status_code == 429
                error = json.loads(refusal.response.body or b"{}")["error"]
                assert error["data"]["reason"] == "sessions", error
                assert (
                    "the token 'vera' has 3 WebSocket connections open, the most one token may "
                    "have ([api] sessions_per_token): close one first" in error["message"]
                )
            # A one-shot token (the dashboard's) counts as the token that fetched it.
            reader, writer = await asyncio.open_connection("127.0.0.1", served.port)
            writer.write(
                b"GET /access/oneshot_token HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                + f"Authorization: Bearer {viewer}\r\nConnection: close\r\n\r\n".encode()
            )
            async with asyncio.timeout(30):
                oneshot = json.loads((await reader.read()).partition(b"\r\n\r\n")[2])["token"]
            writer.close()
            with pytest.raises(InvalidStatus) as caught:
                async with connect(f"ws://127.0.0.1:{served.port}/websocket?token={oneshot}"):
                    pass
            assert caught.value.response.status_code == 429
            # The operator reaches the cell: a WebSocket and a dashboard call.
            async with await served.ws(operator) as ws:
                await ws.send(call(1, "orders.submit", {"part_type": "wax-robot-base", "id": "E1"}))
                assert "result" in await answer(ws, 1)
            reader, writer = await asyncio.open_connection("127.0.0.1", served.port)
            body = b'{"method": "orders.list"}'
            writer.write(
                b"POST /dashboard/call HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                + f"Authorization: Bearer {operator}\r\nContent-Type: application/json\r\n".encode()
                + f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode()
                + body
            )
            async with asyncio.timeout(30):
                data = await reader.read()
            writer.close()
            assert data.startswith(b"HTTP/1.1 200") and b'"E1"' in data, data
            # One of the viewer's closed: it may open another (once the server saw it go).
            await held.pop().close()
            async with asyncio.timeout(30):
                while True:
                    try:
                        held.append(await served.ws(viewer))
                        break
                    except InvalidStatus as e:
                        assert e.response.status_code == 429
                        await asyncio.sleep(0.05)
        finally:
            for ws in held:
                await ws.close()


def test_sessions_per_token_comes_from_cell_toml_below_max_connections(cell: Path) -> None:
    toml = cell / "cell.toml"
    base = toml.read_text()
    toml.write_text(base + "\n[api]\nmax_connections = 10\nsessions_per_token = 4\n")
    config, problems = check_cell(cell)
    assert config is not None, problems
    assert api_limits(config.api).sessions_per_token == 4
    toml.write_text(base + "\n[api]\nmax_connections = 10\nsessions_per_token = 10\n")
    _, problems = check_cell(cell)
    assert any(
        "sessions_per_token = 10 is not less than max_connections = 10: one token could take "
        "every connection" in p
        for p in problems
    ), problems
    # Left at its default under a small max_connections, it stays below it.
    toml.write_text(base + "\n[api]\nmax_connections = 4\n")
    config, problems = check_cell(cell)
    assert config is not None, problems
    assert api_limits(config.api).sessions_per_token == 3
