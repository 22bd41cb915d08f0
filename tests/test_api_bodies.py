"""Request bodies and slow clients, as a caller without a token meets them: a body over a
route's cap is refused before it is read (a Content-Length) or as soon as it passes the cap
(chunked), a client gone mid-body leaves no traceback, and neither an ``Upgrade`` header nor
a chunked body slips past the head's and the body's deadlines. Real servers over real
sockets, standalone on a copy of the example cell."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path

from cellctl.service.server import ApiLimits
from tests.conftest import until
from tests.test_api_hardening import cell as cell  # the fixture: a copy of the example cell
from tests.test_api_hardening import drip, serve, until_closed

#: The body's and the head's deadline here (s): the tests wait for it, bounded, never time it.
DEADLINE = 1.0
MIB_300 = 300 * 1024 * 1024


def post(path: str, *extra: str) -> bytes:
    """A POST's head (no body), with ``extra`` header lines."""
    lines = [f"POST {path} HTTP/1.1", "Host: 127.0.0.1", *extra]
    return ("\r\n".join([*lines, "", ""])).encode()


async def answered(port: int, head: bytes, body: bytes = b"") -> bytes:
    """What the server sent on a connection given ``head`` and ``body`` and no more, until
    it closed it."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(head + body)
        return await until_closed(reader)
    finally:
        writer.close()


def chunk(data: bytes) -> bytes:
    return b"%x\r\n%s\r\n" % (len(data), data)


@contextlib.contextmanager
def server_log() -> Iterator[list[logging.LogRecord]]:
    """The records uvicorn logs (its loggers do not reach pytest's caplog). Enter it once
    the server runs: uvicorn's logging setup drops the handlers its loggers had."""
    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    handler = Keep(logging.DEBUG)
    logger = logging.getLogger("uvicorn")
    logger.addHandler(handler)
    try:
        yield records
    finally:
        logger.removeHandler(handler)


# -- the cap, before the body is read ------------------------------------------------------------


async def test_a_huge_content_length_is_refused_before_its_body_is_read(cell: Path) -> None:
    async with serve(cell, ApiLimits(header_timeout=DEADLINE)) as served:
        token = f"Authorization: Bearer {served.server.token}"
        json_type = "Content-Type: application/json"
        huge = f"Content-Length: {MIB_300}"
        # No byte of the 300 MiB is sent: an answer at all means the body was never awaited
        # (a server reading first would answer 408, the body not come by its deadline).
        data = await answered(served.port, post("/dashboard/handover", huge, json_type))
        assert data.startswith(b"HTTP/1.1 413"), data
        assert b"the request's body is 314,572,800 bytes; at most 1,024 bytes" in data
        data = await answered(served.port, post("/dashboard/call", token, huge, json_type))
        assert data.startswith(b"HTTP/1.1 413"), data
        assert b"at most 65,536 bytes are taken" in data
        # Without the token the call is refused for it, its body never read.
        data = await answered(served.port, post("/dashboard/call", huge, json_type))
        assert data.startswith(b"HTTP/1.1 401") and data.count(b"HTTP/1.1") == 1, data
        assert b"missing or wrong API token" in data


async def test_a_chunked_body_is_refused_as_soon_as_it_passes_the_cap(cell: Path) -> None:
    async with serve(cell, ApiLimits(header_timeout=60)) as served:
        chunked = "Transfer-Encoding: chunked"
        json_type = "Content-Type: application/json"
        # Its last chunk never comes: the answer, before it, is all the server held.
        head = post("/dashboard/handover", chunked, json_type)
        data = await answered(served.port, head, chunk(b"x" * 1025))
        assert data.startswith(b"HTTP/1.1 413"), data
        assert b"the request's body is over 1,024 bytes" in data
        token = f"Authorization: Bearer {served.server.token}"
        head = post("/dashboard/call", token, chunked, json_type)
        data = await answered(served.port, head, chunk(b"x" * 40_000) * 2)
        assert data.startswith(b"HTTP/1.1 413"), data
        assert b"the request's body is over 65,536 bytes" in data


async def test_a_call_under_the_cap_is_served_chunked_or_not(cell: Path) -> None:
    async with serve(cell) as served:
        token = f"Authorization: Bearer {served.server.token}"
        json_type = "Content-Type: application/json"
        call = b'{"method": "cell.status"}'
        for framing, body in (
            (f"Content-Length: {len(call)}", call),
            ("Transfer-Encoding: chunked", chunk(call[:10]) + chunk(call[10:]) + b"0\r\n\r\n"),
        ):
            head = post("/dashboard/call", token, json_type, framing, "Connection: close")
            data = await answered(served.port, head, body)
            assert data.startswith(b"HTTP/1.1 200") and b'"access": "standalone"' in data, data


async def test_a_client_gone_mid_body_leaves_no_traceback(cell: Path) -> None:
    async with serve(cell) as served:
        with server_log() as records:  # after uvicorn set its loggers up
            token = f"Authorization: Bearer {served.server.token}"
            json_type = "Content-Type: application/json"
            for head in (
                post("/dashboard/handover", json_type, "Content-Length: 1000"),
                post("/dashboard/call", token, json_type, "Content-Length: 5000"),
                post("/dashboard/call", token, json_type, "Transfer-Encoding: chunked"),
            ):
                _, writer = await asyncio.open_connection("127.0.0.1", served.port)
                writer.write(head + b'{"code": "abc", ')
                await writer.drain()
                writer.close()
            listeners = served.server._server.listeners  # type: ignore[union-attr]
            await until(lambda: not any(lst.open for lst in listeners), "each seen gone", 30)
            # A request after them is served (their handlers ended before it was answered).
            data = await answered(
                served.port,
                b"GET /server/info HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                + f"{token}\r\nConnection: close\r\n\r\n".encode(),
            )
            assert data.startswith(b"HTTP/1.1 200"), data
    errors = [r for r in records if r.levelno >= logging.ERROR or r.exc_info]
    assert not errors, [r.getMessage() for r in errors]


# -- the deadlines hold for an Upgrade header and a chunked body ---------------------------------


async def test_an_upgrade_header_does_not_lift_the_next_heads_deadline(cell: Path) -> None:
    async with serve(cell, ApiLimits(header_timeout=DEADLINE)) as served:
        reader, writer = await asyncio.open_connection("127.0.0.1", served.port)
        try:
            writer.write(
                b"GET /favicon.ico HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: foo\r\n"
                b"Connection: Upgrade\r\n\r\n"
            )
            async with asyncio.timeout(30):
                head = await reader.readuntil(b"\r\n\r\n")
                length = int(head.lower().split(b"content-length: ")[1].split(b"\r\n")[0])
                await reader.readexactly(length)
            assert head.startswith(b"HTTP/1.1 200"), head  # no token needed for the icon
            # The next request's head, a byte at a time and never ending.
            writer.write(b"GET /favicon.ico HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
            dripping = asyncio.create_task(drip(writer))
            data = await until_closed(reader)
            dripping.cancel()
        finally:
            writer.close()
    assert data.startswith(b"HTTP/1.1 408"), data
    assert b"no request head within 1 s" in data


async def test_a_chunked_body_that_trickles_in_is_cut_off_at_its_deadline(cell: Path) -> None:
    async with serve(cell, ApiLimits(header_timeout=DEADLINE)) as served:
        json_type = "Content-Type: application/json"
        token = f"Authorization: Bearer {served.server.token}"
        for who in ("the token", "no token"):
            extra = [token] if who == "the token" else []
            head = post("/dashboard/call", *extra, json_type, "Transfer-Encoding: chunked")
            reader, writer = await asyncio.open_connection("127.0.0.1", served.port)
            writer.write(head + b"4000\r\n{")  # a chunk of 16 KiB, a byte every 0.2 s
            dripping = asyncio.create_task(drip(writer))
            data = await until_closed(reader)
            dripping.cancel()
            writer.close()
            if who == "the token":
                assert data.startswith(b"HTTP/1.1 408"), data
                assert b"the request's body did not come within 1 s" in data
            else:  # answered at once; closed all the same at the body's deadline
                assert data.startswith(b"HTTP/1.1 401") and data.count(b"HTTP/1.1") == 1, data


async def test_after_a_whole_chunked_body_the_next_head_has_its_deadline(cell: Path) -> None:
    async with serve(cell, ApiLimits(header_timeout=DEADLINE)) as served:
        token = f"Authorization: Bearer {served.server.token}"
        call = b'{"method": "cell.status"}'
        head = post("/dashboard/call", token, "Content-Type: application/json",
                    "Transfer-Encoding: chunked")  # fmt: skip
        reader, writer = await asyncio.open_connection("127.0.0.1", served.port)
        try:
            # A chunk extension and a trailer: the body ends after the trailer's blank line.
            writer.write(head + b"%x;note=1\r\n%s\r\n0\r\nX-Sum: 1\r\n\r\n" % (len(call), call))
            async with asyncio.timeout(30):
                answer = await reader.readuntil(b"\r\n\r\n")
                length = int(answer.lower().split(b"content-length: ")[1].split(b"\r\n")[0])
                assert b"standalone" in await reader.readexactly(length)
            assert answer.startswith(b"HTTP/1.1 200"), answer
            writer.write(b"GET /server/info HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
            dripping = asyncio.create_task(drip(writer))
            data = await until_closed(reader)
            dripping.cancel()
        finally:
            writer.close()
    assert data.startswith(b"HTTP/1.1 408") and b"no request head within 1 s" in data, data


async def test_a_websocket_outlives_the_deadlines_once_upgraded(cell: Path) -> None:
    async with (
        serve(cell, ApiLimits(header_timeout=DEADLINE)) as served,
        await served.ws() as ws,
    ):
        # A head that never ends on another connection: closed at its deadline ...
        reader, writer = await asyncio.open_connection("127.0.0.1", served.port)
        writer.write(b"GET /server/info HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        data = await until_closed(reader)
        writer.close()
        assert data.startswith(b"HTTP/1.1 408"), data
        # ... while the WebSocket, older than that deadline, still answers.
        await ws.send('{"jsonrpc": "2.0", "id": 1, "method": "server.info"}')
        async with asyncio.timeout(30):
            assert '"standalone"' in str(await ws.recv())
