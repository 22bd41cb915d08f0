"""What the control API's listeners allow a connection: how long it may take to send a request's
head, how long it may sit idle, how many may be open at once, and which host names it may ask
for. ``[api]`` of cell.toml sets them::

    limits = ApiLimits(header_timeout=10, idle_timeout=60, max_connections=100, hosts=("cell7",))
    server = GuardedServer(config, limits, listen=("127.0.0.1", 7125))
    await server.serve(sockets=[unix_socket, tcp_socket])   # each socket its own count

- A connection whose request head (request line and headers) is not complete
  ``header_timeout`` s after it began is answered 408 and closed (a slowloris client holds
  nothing for long). The deadline runs for every request of a kept-alive connection.
- A request's body (its Content-Length, or chunked to its last chunk) must have come whole
  ``header_timeout`` s after its head ended; else the connection is closed (answered 408 if
  nothing was answered yet). A client that trickles a body (answered 401 already, or not)
  holds its connection no longer. Only a WebSocket handshake answered ``101`` ends the watch
  on a connection: an ``Upgrade`` header alone changes nothing.
- A WebSocket session has at most ``calls_per_session`` calls in flight, and one token at
  most ``calls_per_token`` over all its sessions; the server refuses more (``server.py``).
- One token holds at most ``sessions_per_token`` WebSockets open; the next handshake is
  answered 429 with the reason (``server.py``), so one token cannot fill the listener.
- Between requests, uvicorn closes a connection idle for ``idle_timeout`` s. A WebSocket is
  kept as long as it answers pings.
- A listener with ``max_connections`` open connections makes room for the next one by
  closing the connection that has waited longest for its next request (a kept-alive one
  whose answer is complete, or one whose request head has not come): a client needs no token
  to hold a connection, so idle ones must not lock the others out. Only when every one is
  busy (a request being answered, a WebSocket) is the new one answered 503, with the reason,
  and closed. Refusals and closings are logged (at most one line per 10 s).
- :class:`HostCheck` answers 421 to a request whose ``Host`` is not a name the listener
  answers to: its address, ``localhost``, a loopback address, or one of ``hosts``. A page
  that reached a loopback port by rebinding its own DNS name is refused, token or not.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import itertools
import json
import logging
import re
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import uvicorn
from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from cellctl.clock import current_clock

if TYPE_CHECKING:
    from cellctl.cell.config import ApiTable

log = logging.getLogger(__name__)

#: The longest request head watched (h11 itself refuses one over 16 KiB).
MAX_HEAD = 64 * 1024
#: Refusals and closings of one listener are logged at most this often.
LOG_EVERY = 10.0
#: What a page served here may load: its own assets only.
CSP = (
    "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
    "connect-src 'self'; font-src 'self'; base-uri 'none'; form-action 'self'; "
    "frame-ancestors 'none'"
)


@dataclass(frozen=True)
class ApiLimits:
    """The limits of every listener of one API server (see the module docstring)."""

    header_timeout: float = 10.0
    idle_timeout: float = 60.0
    max_connections: int = 100
    hosts: tuple[str, ...] = ()
    #: Calls one WebSocket session may have in flight (a batch is one); more are refused.
    calls_per_session: int = 16
    #: Calls one token may have in flight over all its sessions (an acting call whose
    #: client left counts until it ends); more are refused.
    calls_per_token: int = 32
    #: WebSockets one token may hold open at once, over every listener (a one-shot token's
    #: count as its token's): one token cannot take every connection of ``max_connections``.
    sessions_per_token: int = 8


def api_limits(table: ApiTable | None) -> ApiLimits:
    """The limits ``[api]`` of cell.toml sets (the defaults without one)."""
    if table is None:
        return ApiLimits()
    return ApiLimits(
        header_timeout=table.header_timeout,
        idle_timeout=table.idle_timeout,
        max_connections=table.max_connections,
        hosts=tuple(table.hosts),
        calls_per_session=table.calls_per_session,
        calls_per_token=table.calls_per_token,
        # Left at its default under a small max_connections: still below it.
        sessions_per_token=max(1, min(table.sessions_per_token, table.max_connections - 1)),
    )


class Listener:
    """One listening socket's open connections, and its rate-limited log."""

    def __init__(self, name: str, limits: ApiLimits) -> None:
        self.name = name
        self.limits = limits
        self.guards: set[_Guard] = set()  # its open connections
        self.refused = 0
        self.evicted = 0
        self.timed_out = 0
        self._logged: dict[str, float] = {}
        self._untold: dict[str, int] = {}

    @property
    def open(self) -> int:
        """How many connections are open (one closed to make room counts no more at once)."""
        return len(self.guards)

    def make_room(self) -> bool:
        """Close the connection that has waited longest for its next request (one closing
        already first) to let a new one in; False if every one is busy."""
        idle = [guard for guard in self.guards if guard.idle()]
        if not idle:
            return False
        min(idle, key=lambda guard: (not guard.closing(), guard.since)).evict()
        return True

    def note(self, kind: str, text: str) -> None:
        """Log ``text`` unless a line of this ``kind`` went out in the last LOG_EVERY s."""
        now = current_clock().monotonic()
        if now - self._logged.get(kind, -LOG_EVERY) < LOG_EVERY:
            self._untold[kind] = self._untold.get(kind, 0) + 1
            return
        more = self._untold.pop(kind, 0)
        self._logged[kind] = now
        log.warning("API %s: %s%s", self.name, text, f" (and {more} more)" if more else "")


def _http(status: str, reason: str) -> bytes:
    body = (reason + "\n").encode()
    head = (
        f"HTTP/1.1 {status}\r\nContent-Type: text/plain; charset=utf-8\r\n"
        f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
    )
    return head.encode() + body


_HEAD, _BODY, _CHUNKED, _IDLE, _PAST = range(5)
#: The order in which connections began to wait for a request (connected, or answered).
_ticks = itertools.count()
#: An attribute a protocol does not have.
_MISSING = object()


class _Guard(asyncio.Protocol):
    """The protocol a listener's connections really have: it counts them, holds the header
    deadline, and hands every byte to uvicorn's protocol (``inner``) unchanged."""

    def __init__(self, listener: Listener, make: Callable[[], asyncio.Protocol]) -> None:
        self.listener = listener
        self.make = make
        self.inner: asyncio.BaseProtocol | None = None
        self.transport: asyncio.Transport | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._mode = _HEAD
        self._head = bytearray()
        self._left = 0
        self._answered = False  # something was written since the request's head ended
        self._upgrading = False  # uvicorn's WebSocket protocol has the connection
        self._line = bytearray()  # a chunked body's size or trailer line, so far
        self._trailer = False  # a chunked body's last chunk came: its trailer lines follow
        self.since = next(_ticks)  # when it began to wait for its next request

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        listener = self.listener
        if listener.open >= listener.limits.max_connections and not listener.make_room():
            listener.refused += 1
            reason = (
                f"refused: {listener.open} connections are open on this listener, "
                f"the most [api] max_connections allows, and every one is busy"
            )
            listener.note("refused", f"{reason} ({listener.refused} so far)")
            transport.write(_http("503 Service Unavailable", reason))
            transport.close()
            return
        listener.guards.add(self)
        self.inner = self.make()
        self._arm()
        self.inner.connection_made(_Transport(transport, self))

    def data_received(self, data: bytes) -> None:
        if self.inner is None:
            return
        if self._mode is not _PAST:
            self._watch(data)
        if isinstance(self.inner, asyncio.Protocol):
            self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        if isinstance(self.inner, asyncio.Protocol):
            return self.inner.eof_received()
        return None

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        if self.inner is not None:
            self.listener.guards.discard(self)  # gone from the count already if evicted
            self.inner.connection_lost(exc)

    def pause_writing(self) -> None:
        if self.inner is not None:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.inner is not None:
            self.inner.resume_writing()

    def idle(self) -> bool:
        """Whether it waits for its client, not the server: no request yet, or its answer
        complete (as uvicorn's shutdown judges it), or a request's body still to come; or it
        is being closed (it goes anyway). A WebSocket, or a protocol not known here, is busy."""
        if self.inner is None:
            return False
        if self.closing():  # a refused handshake's, say: its connection_lost is yet to come
            return True
        if self._mode in (_BODY, _CHUNKED):
            # Its client still owes the request's body: a client on this host sends one whole
            # at once, and one that trickles it (a route that reads it before the token is
            # checked) must not hold the connection from the others.
            return True
        if self._upgrading:
            return False
        cycle = getattr(self.inner, "cycle", _MISSING)
        if cycle is _MISSING:
            return False
        return cycle is None or getattr(cycle, "response_complete", False) is True

    def closing(self) -> bool:
        """Whether its socket is being closed already."""
        return self.transport is None or self.transport.is_closing()

    def evict(self) -> None:
        """Close it to make room for a new connection, and count it out at once (its
        ``connection_lost`` may come later)."""
        listener = self.listener
        listener.guards.discard(self)
        if self.transport is None:
            return
        if not self.transport.is_closing():  # one closing already is no news
            listener.evicted += 1
            peer = self.transport.get_extra_info("peername") or "the socket"
            listener.note(
                "evicted",
                f"closed an idle connection from {peer}: the listener was full "
                f"([api] max_connections; {listener.evicted} so far)",
            )
        if self.transport.get_write_buffer_size():
            # An answer its client does not read: closing would wait for it without end.
            self.transport.abort()
        else:
            self.transport.close()

    def upgraded(self, protocol: asyncio.BaseProtocol) -> None:
        """uvicorn swapped in its WebSocket protocol for a handshake. The deadlines hold until
        the handshake is answered 101 (:meth:`wrote`): a request that only says ``Upgrade``
        gets no pass."""
        self.inner = protocol
        self._upgrading = True

    def wrote(self, first: bytes | bytearray | memoryview) -> None:
        """uvicorn wrote to the connection (an answer, maybe before the body has come); after
        ``101 Switching Protocols`` it is a WebSocket, no HTTP any more: nothing to watch."""
        self._answered = True
        self.since = next(_ticks)
        if self._upgrading and bytes(first[:13]) == b"HTTP/1.1 101 ":
            self._mode = _PAST
            self._disarm()

    # -- the request head's and body's deadlines ---------------------------------------------

    def _arm(self, expired: Callable[[], None] | None = None) -> None:
        self._disarm()
        loop = asyncio.get_running_loop()
        limit = self.listener.limits.header_timeout
        self._timer = loop.call_later(limit, expired or self._too_slow)

    def _disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _too_slow(self) -> None:
        self._close_slow("no request head within {s} s", "no request head within {s} s", head=True)

    def _body_too_slow(self) -> None:
        self._close_slow(
            "a request's body not whole within {s} s",
            "the request's body did not come within {s} s",
        )

    def _close_slow(self, noted: str, told: str, *, head: bool = False) -> None:
        """Close a connection whose request ``head`` or body came too slowly: ``noted`` for
        the listener's notes, ``told`` to the client (408), for a body unless an answer went
        out already (a second would garble it); ``{s}`` in both is the limit."""
        self._timer = None
        if self.transport is None or self.transport.is_closing():
            return
        seconds = f"{self.listener.limits.header_timeout:g}"
        self.listener.timed_out += 1
        peer = self.transport.get_extra_info("peername") or "the socket"
        self.listener.note("timeout", f"closed a connection from {peer}: {noted.format(s=seconds)}")
        if head or not self._answered:
            with contextlib.suppress(Exception):
                self.transport.write(
                    _http("408 Request Timeout", f"closed: {told.format(s=seconds)}")
                )
        self.transport.close()

    def _watch(self, data: bytes) -> None:
        """Follow the requests' heads and bodies (Content-Length or chunked) to know when one
        begins and when its body is whole."""
        i = 0
        while i < len(data) and self._mode is not _PAST:
            if self._mode == _BODY:
                take = min(self._left, len(data) - i)
                self._left -= take
                i += take
                if not self._left:
                    self._mode = _IDLE
                    self._disarm()
            elif self._mode == _CHUNKED:
                i = self._chunked(data, i)
            elif self._mode == _IDLE:
                self._mode = _HEAD
                self._head.clear()
                self._arm()
            else:
                before = len(self._head)
                self._head += data[i:]
                end = self._head.find(b"\r\n\r\n", max(0, before - 3))
                if end < 0:
                    if len(self._head) > MAX_HEAD:
                        self._mode = _PAST  # h11 refuses it; the deadline stays armed
                    return
                i += end + 4 - before
                head = bytes(self._head[:end])
                self._head.clear()
                self._disarm()
                self._answered = False
                self._mode, self._left = _after(head)
                self._line.clear()
                self._trailer = False
                if self._mode != _IDLE:
                    # The whole body, from the head's end (a head h11 refuses: a backstop).
                    self._arm(self._body_too_slow)

    def _chunked(self, data: bytes, i: int) -> int:
        """Follow a chunked body in ``data`` from ``i``: sizes, data, the last chunk's
        trailer. Where it stopped (the body whole: the next request's head begins there)."""
        while i < len(data):
            if self._left:  # a chunk's data and the CRLF after it
                take = min(self._left, len(data) - i)
                self._left -= take
                i += take
                continue
            end = data.find(b"\n", i)
            if end < 0:
                self._line += data[i:]
                if len(self._line) > MAX_HEAD:
                    self._mode = _PAST  # h11 refuses it; the deadline stays armed
                return len(data)
            self._line += data[i:end]
            i = end + 1
            line = bytes(self._line).strip()
            self._line.clear()
            if self._trailer:
                if not line:  # the blank line after the trailer: the body is whole
                    self._mode = _IDLE
                    self._disarm()
                    return i
                continue
            size = _CHUNK_SIZE.fullmatch(line)
            if size is None:
                self._mode = _PAST  # h11 refuses it; the deadline stays armed
                return len(data)
            length = int(size.group(1), 16)
            self._trailer = length == 0
            self._left = length + 2 if length else 0
        return i


#: A chunk's size line: hex digits, maybe extensions after ``;``.
_CHUNK_SIZE = re.compile(rb"([0-9A-Fa-f]{1,16})[ \t]*(?:;.*)?")


def _after(head: bytes) -> tuple[int, int]:
    """What follows a request head: a body of some length, a chunked body, the next head, or
    something h11 refuses (watched no more; the body's deadline closes it if it lingers).
    An ``Upgrade`` header changes nothing here: only a 101 answer ends the watch."""
    length = 0
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        name = name.strip().lower()
        if name == b"transfer-encoding":
            codings = [c.strip() for c in value.lower().split(b",")]
            return (_CHUNKED, 0) if codings[-1] == b"chunked" else (_PAST, 0)
        if name == b"content-length":
            try:
                length = int(value.strip())
            except ValueError:
                return _PAST, 0
    return (_BODY, length) if length > 0 else (_IDLE, 0)


class _Transport(asyncio.Transport):
    """The transport uvicorn's protocol sees: the real one, except that a switch of protocol
    (the WebSocket upgrade) goes to the guard, which stays the socket's protocol."""

    def __init__(self, real: asyncio.Transport, guard: _Guard) -> None:
        super().__init__()
        self._real = real
        self._guard = guard

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return self._real.get_extra_info(name, default)

    def is_closing(self) -> bool:
        return self._real.is_closing()

    def close(self) -> None:
        self._real.close()

    def set_protocol(self, protocol: asyncio.BaseProtocol) -> None:
        self._guard.upgraded(protocol)

    def get_protocol(self) -> asyncio.BaseProtocol:
        return self._guard.inner or self._guard

    def is_reading(self) -> bool:
        return self._real.is_reading()

    def pause_reading(self) -> None:
        self._real.pause_reading()

    def resume_reading(self) -> None:
        self._real.resume_reading()

    def set_write_buffer_limits(self, high: int | None = None, low: int | None = None) -> None:
        self._real.set_write_buffer_limits(high, low)

    def get_write_buffer_size(self) -> int:
        return self._real.get_write_buffer_size()

    def get_write_buffer_limits(self) -> tuple[int, int]:
        return self._real.get_write_buffer_limits()

    def write(self, data: bytes | bytearray | memoryview) -> None:
        self._guard.wrote(data)
        self._real.write(data)

    def writelines(self, list_of_data: Any) -> None:
        pieces = list(list_of_data)
        self._guard.wrote(pieces[0] if pieces else b"")
        self._real.writelines(pieces)

    def write_eof(self) -> None:
        self._real.write_eof()

    def can_write_eof(self) -> bool:
        return self._real.can_write_eof()

    def abort(self) -> None:
        self._real.abort()


class GuardedServer(uvicorn.Server):
    """uvicorn on the given sockets, each behind its own :class:`Listener`; without uvicorn's
    signal handlers (the controller's own handle Ctrl-C)."""

    def __init__(self, config: uvicorn.Config, limits: ApiLimits) -> None:
        super().__init__(config)
        self.limits = limits
        self.listeners: list[Listener] = []

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        yield

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        config = self.config
        loop = asyncio.get_running_loop()

        def uvicorn_protocol() -> asyncio.Protocol:
            protocol: asyncio.Protocol = config.http_protocol_class(  # type: ignore[call-arg]
                config=config, server_state=self.server_state, app_state=self.lifespan.state
            )
            return protocol

        self.servers = []
        for sock in sockets or []:
            name = sock.getsockname()
            # A Unix socket keeps the name it was bound under; the server renames the file
            # from ``api.sock~`` once it listens (server.py), and users know it as api.sock.
            shown = str(name).removesuffix("~") if name else "socket"
            listener = Listener(shown, self.limits)
            self.listeners.append(listener)
            server = await loop.create_server(
                lambda listener=listener: _Guard(listener, uvicorn_protocol),  # type: ignore[misc]
                sock=sock,
                backlog=config.backlog,
            )
            self.servers.append(server)
        self.started = True


def host_name(header: str) -> str:
    """The name in a Host header, without its port: ``[::1]:7125`` → ``::1``."""
    text = header.strip().lower()
    if text.startswith("["):
        return text[1:].partition("]")[0]
    if text.count(":") == 1:
        text = text.partition(":")[0]
    return text.rstrip(".")


def allowed_host(name: str, listen: str | None, hosts: tuple[str, ...]) -> bool:
    """Whether a listener on ``listen`` (a host, or None for the Unix socket) answers to
    ``name``: its own address, localhost, a loopback address, or one of ``hosts``."""
    if not name:
        return False
    if name == "localhost" or name in {h.lower().rstrip(".") for h in hosts}:
        return True
    try:
        address = ipaddress.ip_address(name)
    except ValueError:
        return False
    if address.is_loopback or (listen is not None and name == listen.lower()):
        return True
    # A listener on every address answers to each of them; an address is never rebound.
    return listen in ("0.0.0.0", "::")


class HostCheck:
    """Refuse (421, with the reason) a request whose Host is not one the server answers to."""

    def __init__(self, app: ASGIApp, listen: str | None, hosts: tuple[str, ...]) -> None:
        self.app = app
        self.listen = listen
        self.hosts = hosts
        self.refused = Listener("Host check", ApiLimits())

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        header = dict(scope.get("headers") or []).get(b"host", b"").decode("latin-1")
        name = host_name(header)
        if allowed_host(name, self.listen, self.hosts):
            await self.app(scope, receive, send)
            return
        reason = (
            f"refused: this server does not answer to the host name {header[:100]!r} "
            "(a page of another site, reaching it by DNS rebinding?); "
            "if the name is yours, add it to [api] hosts in cell.toml"
        )
        self.refused.note("host", reason)
        body = json.dumps({"error": {"code": -32007, "message": reason}}).encode()
        prefix = "websocket.http" if scope["type"] == "websocket" else "http"
        headers = [(b"content-type", b"application/json"), (b"content-length", b"%d" % len(body))]
        await send({"type": f"{prefix}.response.start", "status": 421, "headers": headers})
        await send({"type": f"{prefix}.response.body", "body": body})


class SecurityHeaders:
    """Every HTTP answer: the Content-Security-Policy, no sniffing, no framing, no caching of
    cell data."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                headers.setdefault("Content-Security-Policy", CSP)
                headers.setdefault("X-Content-Type-Options", "nosniff")
                headers.setdefault("X-Frame-Options", "DENY")
                headers.setdefault("Referrer-Policy", "no-referrer")
                headers.setdefault("Cache-Control", "no-store")
            await send(message)

        await self.app(scope, receive, with_headers)
