"""The control API's limits, as an attacker on the box meets them: the token file, JSON-RPC
batches, bounds on every parameter, slow and too many connections, and the Host header.
The server runs standalone (no controller) on a copy of the example cell, over real sockets."""

from __future__ import annotations

import asyncio
import json
import logging
import shutil
import stat
import subprocess
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import InvalidStatus

from cellctl.cell.config import check_cell
from cellctl.cell.journal import open_journal
from cellctl.errors import UsageError
from cellctl.mailbox import open_mailbox
from cellctl.service.access import LocalCell
from cellctl.service.client import RemoteCell
from cellctl.service.server import ApiLimits, ApiServer, api_limits, ensure_token, parse_listen
from cellctl.ui.dashboard.routes import dashboard_routes
from tests.conftest import CELLCTL, free_port, until

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell"
HEADER_TIMEOUT = 0.5


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    shutil.copytree(EXAMPLE, directory)
    open_journal(directory).close()
    return directory


@dataclass
class Served:
    server: ApiServer
    port: int
    token: str

    async def ws(self, **kwargs: Any) -> ClientConnection:
        headers = {"Authorization": f"Bearer {self.token}"}
        return await connect(
            f"ws://127.0.0.1:{self.port}/websocket",
            additional_headers=headers,
            max_size=None,
            **kwargs,
        )


@pytest.fixture
async def served(cell: Path) -> AsyncIterator[Served]:
    port = free_port()
    limits = ApiLimits(header_timeout=HEADER_TIMEOUT, hosts=("cell7.lab",))
    async with LocalCell(cell, {}) as access:
        server = ApiServer(
            access,
            cell,
            listen=f"127.0.0.1:{port}",
            extra_routes=dashboard_routes,
            limits=limits,
        )
        await server.start()
        try:
            yield Served(server, port, server.token)
        finally:
            await server.close()


async def http(port: int, request: bytes) -> tuple[int, bytes]:
    """Send ``request`` as is; the status and body of the answer (the server closes)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(request)
        async with asyncio.timeout(10):
            data = await reader.read()
    finally:
        writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), body


def get(path: str, host: str, token: str, *extra: str) -> bytes:
    lines = [f"GET {path} HTTP/1.1", f"Host: {host}", f"Authorization: Bearer {token}", *extra]
    return ("\r\n".join([*lines, "Connection: close", "", ""])).encode()


# -- finding 4: the token file ------------------------------------------------------------------


def test_a_link_in_place_of_the_token_is_refused_never_followed(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    cell.mkdir()
    target = tmp_path / "target"
    target.write_text("x\n")
    target.chmod(0o644)
    (cell / "api-token").symlink_to(target)
    with pytest.raises(UsageError, match=r"symbolic link.*remove .*api-token"):
        ensure_token(cell)
    assert target.read_text() == "x\n" and stat.S_IMODE(target.stat().st_mode) == 0o644
    # A link to nowhere: no token is written at its target.
    (cell / "api-token").unlink()
    (cell / "api-token").symlink_to(tmp_path / "nowhere")
    with pytest.raises(UsageError, match="symbolic link"):
        ensure_token(cell)
    assert not (tmp_path / "nowhere").exists()


def test_a_short_token_is_refused_and_a_new_one_is_made_once_removed(tmp_path: Path) -> None:
    path = tmp_path / "api-token"
    path.write_text("x\n")
    with pytest.raises(UsageError, match=r"at least 32 characters.*remove"):
        ensure_token(tmp_path)
    path.unlink()
    token = ensure_token(tmp_path)
    assert len(token) >= 32 and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert ensure_token(tmp_path) == token


def test_cellctl_run_refuses_a_linked_token_with_exit_2(cell: Path, tmp_path: Path) -> None:
    target = tmp_path / "elsewhere"
    target.write_text("y" * 40 + "\n")
    (cell / "api-token").symlink_to(target)
    run = subprocess.run(
        [*CELLCTL, "--cell", str(cell), "run"], capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 2, run.stdout + run.stderr
    assert "symbolic link" in run.stderr and "remove" in run.stderr
    assert "Traceback" not in run.stdout + run.stderr


# -- finding 5: batches -------------------------------------------------------------------------


def call(rid: int | None, method: str, params: dict[str, Any] | None = None) -> dict[str, Any]:
    request: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "params": params or {}}
    if rid is not None:
        request["id"] = rid
    return request


async def test_a_batch_is_answered_as_one_array(served: Served) -> None:
    async with await served.ws() as ws:
        batch = [call(1, "server.info"), call(None, "cell.status"), {"id": 3}, call(4, "x.y")]
        await ws.send(json.dumps(batch))
        answers = json.loads(await ws.recv())
        assert isinstance(answers, list)
        by_id = {a["id"]: a for a in answers}
        assert set(by_id) == {1, 3, 4}  # the notification gets no answer
        assert by_id[1]["result"]["mode"] == "standalone"
        assert by_id[3]["error"]["code"] == -32600
        assert by_id[4]["error"]["code"] == -32601
    url = f"ws://127.0.0.1:{served.port}"
    async with await RemoteCell.connect(token=served.token, url=url) as client:
        assert (await client.call("server.info"))["mode"] == "standalone"


async def test_a_batch_over_100_requests_gets_one_refusal(served: Served) -> None:
    async with await served.ws() as ws, await served.ws() as other:
        for size in (101, 30_000):
            await ws.send(json.dumps([call(i, "cell.status") for i in range(size)]))
            await other.send(json.dumps(call(1, "server.info")))
            assert json.loads(await other.recv())["id"] == 1  # the other client is served
            refusal = json.loads(await ws.recv())
            assert refusal["id"] is None and refusal["error"]["code"] == -32600
            assert f"batch of {size} requests; at most 100" in refusal["error"]["message"]
            # Nothing else came of it: the next message is the answer to the next call.
            await ws.send(json.dumps(call(7, "server.info")))
            assert json.loads(await ws.recv())["id"] == 7


async def test_another_client_is_answered_while_a_batch_runs(served: Served) -> None:
    arrived: list[str] = []
    async with await served.ws() as ws, await served.ws() as other:
        await ws.send(json.dumps([call(i, "cell.status") for i in range(100)]))
        await other.send(json.dumps(call(1, "server.info")))

        async def take(conn: ClientConnection, name: str) -> Any:
            message = json.loads(await conn.recv())
            arrived.append(name)
            return message

        async with asyncio.timeout(30):
            batch, single = await asyncio.gather(take(ws, "batch"), take(other, "single"))
    assert arrived == ["single", "batch"]
    assert [a["id"] for a in batch] == list(range(100)) and single["id"] == 1


async def test_a_client_that_leaves_cancels_the_rest_of_its_batch(
    served: Served, cell: Path
) -> None:
    ws = await served.ws()
    orders = [
        call(i, "orders.submit", {"part_type": "wax-robot-base", "id": f"L{i}"}) for i in range(100)
    ]
    await ws.send(json.dumps(orders))
    await ws.close()
    # The server saw the client go (after its batch, which came first), and the batch ended.
    await until(lambda: not served.server.sessions, "the session closed")
    async with asyncio.timeout(30):
        await asyncio.gather(*served.server.calls, return_exceptions=True)
    with open_mailbox(cell) as mailbox:
        posted = [o.id for o in mailbox.orders()]
    assert len(posted) < 100, "the batch went on after its client left"


# -- finding 6: bounds on parameters ------------------------------------------------------------


async def test_out_of_range_parameters_are_invalid_params_not_internal_errors(
    served: Served, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    async with await served.ws() as ws:
        await ws.send(json.dumps(call(1, "alarms.clear", {"id": 2**63})))
        error = json.loads(await ws.recv())["error"]
        assert error["code"] == -32602 and "id" in error["message"], error
        await ws.send(json.dumps(call(2, "orders.list", {"states": ["posted"] * 700_000})))
        error = json.loads(await ws.recv())["error"]
        assert error["code"] == -32602 and "states" in error["message"], error
    body = json.dumps({"method": "alarms.clear", "params": {"id": 2**63}}).encode()
    status, answer = await http(
        served.port,
        b"POST /dashboard/call HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        + f"Authorization: Bearer {served.token}\r\n".encode()
        + b"Content-Type: application/json\r\nConnection: close\r\n"
        + f"Content-Length: {len(body)}\r\n\r\n".encode()
        + body,
    )
    assert status == 400, answer
    assert json.loads(answer)["error"]["code"] == -32602
    assert not [r for r in caplog.records if r.exc_info], "a traceback in the log"


# -- finding 7: slow clients, too many clients --------------------------------------------------


async def test_a_connection_that_never_finishes_its_head_is_closed(served: Served) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", served.port)
    writer.write(b"GET /server/info HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
    async with asyncio.timeout(20):  # the deadline is HEADER_TIMEOUT: this only bounds the test
        data = await reader.read()
    writer.close()
    assert data.startswith(b"HTTP/1.1 408") and b"no request head within 0.5 s" in data
    # So is a kept-alive connection whose second request's head never ends.
    reader, writer = await asyncio.open_connection("127.0.0.1", served.port)
    first = get("/server/info", "127.0.0.1", served.token).replace(b"Connection: close\r\n", b"")
    writer.write(first)
    async with asyncio.timeout(20):
        head = await reader.readuntil(b"\r\n\r\n")
        length = int(head.lower().split(b"content-length: ")[1].split(b"\r\n")[0])
        await reader.readexactly(length)
        assert head.startswith(b"HTTP/1.1 200")
        writer.write(b"GET /server/info HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        rest = await reader.read()
    writer.close()
    assert rest.startswith(b"HTTP/1.1 408")


async def test_the_connection_over_the_cap_is_refused_with_a_reason(cell: Path) -> None:
    port = free_port()
    limits = ApiLimits(header_timeout=60, max_connections=3)
    async with LocalCell(cell, {}) as access:
        server = ApiServer(access, cell, listen=f"127.0.0.1:{port}", limits=limits)
        await server.start()
        held: list[ClientConnection] = []
        try:
            # Busy connections (an idle kept-alive one would be closed to make room).
            for _ in range(3):
                held.append(await Served(server, port, server.token).ws())
            status, body = await http(port, get("/server/info", "127.0.0.1", server.token))
            assert status == 503 and b"3 connections are open on this listener" in body
            await held.pop().close()
            # One closed: a new one is served again (once the server saw it go).
            async with asyncio.timeout(10):
                while True:
                    status, body = await http(port, get("/server/info", "127.0.0.1", server.token))
                    if status == 200:
                        break
                    await asyncio.sleep(0.02)
            assert json.loads(body)["mode"] == "standalone"
        finally:
            for ws in held:
                await ws.close()
            await server.close()


async def test_localhost_is_bound_as_127_0_0_1_never_looked_up(cell: Path) -> None:
    # "localhost" passes as loopback by its name: what is bound must be loopback too, not
    # whatever a hosts file maps the name to (a public address would serve the API there).
    assert parse_listen("localhost:7125", allow_remote=False) == ("127.0.0.1", 7125)
    assert parse_listen("localhost:7130", False, table="dnc") == ("127.0.0.1", 7130)
    port = free_port()
    async with LocalCell(cell, {}) as access:
        server = ApiServer(access, cell, listen=f"localhost:{port}")
        await server.start()
        try:
            assert server.tcp == ("127.0.0.1", port)
            status, body = await http(port, get("/server/info", f"localhost:{port}", server.token))
            assert status == 200 and json.loads(body)["mode"] == "standalone", body
        finally:
            await server.close()


# -- finding 8: the Host header ------------------------------------------------------------------


async def test_a_foreign_host_name_is_refused_even_with_the_token(served: Served) -> None:
    status, body = await http(served.port, get("/api/status", "evil.example", served.token))
    assert status == 421 and b"does not answer to the host name 'evil.example'" in body
    status, body = await http(served.port, get("/api/status", "evil.example:80", served.token))
    assert status == 421
    upgrade = (
        "GET /websocket HTTP/1.1\r\nHost: evil.example\r\nUpgrade: websocket\r\n"
        "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
        f"Sec-WebSocket-Version: 13\r\nAuthorization: Bearer {served.token}\r\n\r\n"
    )
    status, body = await http(served.port, upgrade.encode())
    assert status == 421 and b"DNS rebinding" in body
    for host in (f"127.0.0.1:{served.port}", f"localhost:{served.port}", "cell7.lab", "[::1]"):
        status, body = await http(served.port, get("/api/status", host, served.token))
        assert status == 200, (host, body)
    # The Origin check still holds: a page of another origin on a good Host is refused.
    with pytest.raises(InvalidStatus) as foreign:
        async with connect(
            f"ws://127.0.0.1:{served.port}/websocket",
            additional_headers={"Authorization": f"Bearer {served.token}"},
            origin="http://evil.example",  # type: ignore[arg-type]
        ):
            pass
    assert foreign.value.response.status_code == 403


def test_the_limits_come_from_the_api_table_of_cell_toml(cell: Path) -> None:
    with (cell / "cell.toml").open("a") as f:
        f.write(
            '\n[api]\nlisten = "127.0.0.1:7125"\nhosts = ["cell7.lab"]\nheader_timeout = 2.5\n'
            "idle_timeout = 30\nmax_connections = 8\ncalls_per_session = 4\n"
            "calls_per_token = 6\nsessions_per_token = 5\n"
        )
    config, problems = check_cell(cell)
    assert config is not None, problems
    assert api_limits(config.api) == ApiLimits(
        header_timeout=2.5,
        idle_timeout=30.0,
        max_connections=8,
        hosts=("cell7.lab",),
        calls_per_session=4,
        calls_per_token=6,
        sessions_per_token=5,
    )
    text = (cell / "cell.toml").read_text()
    (cell / "cell.toml").write_text(text.replace("calls_per_token = 6", "calls_per_token = 3"))
    _, problems = check_cell(cell)
    assert any("calls_per_token = 3 is less than calls_per_session = 4" in p for p in problems)
    (cell / "cell.toml").write_text(text)
    text = (cell / "cell.toml").read_text().replace("max_connections = 8", "max_connections = 0")
    (cell / "cell.toml").write_text(text)
    _, problems = check_cell(cell)
    assert any("max_connections" in p for p in problems), problems
