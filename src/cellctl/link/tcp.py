"""Raw TCP serial servers: ``socket://host:port`` (bytes as they are, no modem lines)."""

from __future__ import annotations

import asyncio
import os
import socket

from cellctl.clock import Clock
from cellctl.errors import LinkClosed, LinkError
from cellctl.link.base import Link
from cellctl.link.settings import LineSettings
from cellctl.link.trace import TrafficLog

#: Bytes taken from the socket per read. Records are a few dozen bytes; asyncio's own read
#: size (256 KiB) makes every read allocate and map a fresh buffer, which cost more than the
#: rest of a transaction with thousands of links.
READ_SIZE = 4096


class StreamProtocol(asyncio.BufferedProtocol):
    """Feeds a link from an asyncio transport, read into one buffer of its own."""

    def __init__(self, link: TcpLink) -> None:
        self.link = link
        self.transport: asyncio.Transport | None = None
        self._buffer = bytearray(READ_SIZE)
        self._view = memoryview(self._buffer)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            # Records are a few bytes each: don't let Nagle hold them back.
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def get_buffer(self, sizehint: int) -> memoryview:
        return self._view

    def buffer_updated(self, nbytes: int) -> None:
        self.link._on_wire_data(bytes(self._view[:nbytes]))

    def connection_lost(self, exc: Exception | None) -> None:
        why = f": {exc}" if exc else ""
        self.link._feed_closed(LinkClosed(f"{self.link.url}: the other end closed the link{why}"))


class TcpLink(Link):
    """A TCP connection to a serial device server in raw mode."""

    def __init__(
        self,
        url: str,
        settings: LineSettings,
        trace: TrafficLog | None,
        label: str,
        *,
        clock: Clock | None = None,
    ):
        super().__init__(url, settings, trace, label, clock=clock)
        self._transport: asyncio.Transport | None = None

    async def _connect(self, host: str, port: int, timeout: float) -> None:
        try:
            async with self.clock.timeout(timeout):
                transport, _ = await self._loop.create_connection(
                    lambda: StreamProtocol(self), host, port
                )
        except TimeoutError as e:
            raise LinkError(f"cannot connect to {self.url}: no answer in {timeout:g} s") from e
        except OSError as e:
            # asyncio's strerror ("Connect call failed (...)") says less than the system's.
            why = os.strerror(e.errno) if isinstance(e.errno, int) else (e.strerror or str(e))
            raise LinkError(f"cannot connect to {self.url}: {why.lower()}") from e
        self._transport = transport

    def _on_wire_data(self, data: bytes) -> None:
        self._feed(data)

    async def _send(self, data: bytes) -> None:
        assert self._transport is not None
        if self._transport.is_closing():
            raise self._closed_exc or LinkClosed(f"{self.url}: link closed")
        self._transport.write(data)

    async def _shutdown(self) -> None:
        if self._transport is not None:
            self._transport.close()
