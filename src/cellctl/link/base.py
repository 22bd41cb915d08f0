"""The async byte link every driver talks through, whatever carries the bytes.

A :class:`Link` is bytes in and bytes out with a deadline on every wait; it knows nothing of
any protocol. Subclasses push received bytes with ``_feed`` and implement ``_send`` and
``_shutdown``; everything else (buffering, deadlines, tracing) lives here once.
"""

from __future__ import annotations

import asyncio
from abc import ABC, abstractmethod
from types import TracebackType

from cellctl.clock import Clock, check_loop_clock, current_clock
from cellctl.errors import LinkClosed, LinkError, LinkTimeout, UsageError, format_raw
from cellctl.link.settings import LineSettings
from cellctl.link.trace import RECEIVED, SENT, TrafficLog


class Link(ABC):
    """An open byte link. Use ``async with await open_link(url) as link:``.

    Reads return as soon as bytes are there; every read takes a ``timeout`` in seconds and
    raises :class:`LinkTimeout` when it passes, :class:`LinkClosed` when the other end went
    away. Writes return once the bytes are handed to the OS or network. Deadlines and trace
    stamps are read from ``clock`` (the running loop's :func:`~cellctl.clock.current_clock` if
    None).
    """

    has_modem_lines: bool = False
    """True where the host's CTS (the machine's RTS) can be read: serial ports and RFC 2217."""

    def __init__(
        self,
        url: str,
        settings: LineSettings,
        trace: TrafficLog | None,
        label: str,
        *,
        clock: Clock | None = None,
    ):
        self.url = url
        self.settings = settings
        self.label = label
        self._trace = trace
        self._buf = bytearray()
        self._waiter: asyncio.Future[None] | None = None
        self._wait_until = 0.0
        self._timer: asyncio.TimerHandle | None = None
        self._closed_exc: LinkError | None = None
        self._loop = asyncio.get_running_loop()
        # A link is made in its running loop: its clock can be resolved now.
        self.clock: Clock = clock or current_clock()
        check_loop_clock(self.clock, f"link {url}")
        self.bytes_sent = 0
        self.bytes_received = 0

    # -- for subclasses -------------------------------------------------------------------------

    def _feed(self, data: bytes) -> None:
        """Bytes arrived from the machine."""
        if not data:
            return
        self.bytes_received += len(data)
        if self._trace is not None:
            self._trace.record(self.label, RECEIVED, data, self.clock.now())
        self._buf += data
        self._wake()

    def _feed_closed(self, exc: LinkError | None = None) -> None:
        """The other end closed (or the transport failed)."""
        if self._closed_exc is None:
            self._closed_exc = exc or LinkClosed(f"{self.url}: the other end closed the link")
        self._wake()

    def _wake(self) -> None:
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    @abstractmethod
    async def _send(self, data: bytes) -> None: ...

    @abstractmethod
    async def _shutdown(self) -> None: ...

    # -- public ------------------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        """True once the link is closed, from either end."""
        return self._closed_exc is not None

    async def write(self, data: bytes) -> None:
        """Send ``data``; raises LinkClosed if the link is gone."""
        if self._closed_exc is not None:
            raise self._closed_exc
        if not data:
            return
        if self._trace is not None:
            self._trace.record(self.label, SENT, data, self.clock.now())
        self.bytes_sent += len(data)
        await self._send(data if type(data) is bytes else bytes(data))

    async def _wait(self, deadline: float, wanted: str) -> None:
        """Wait for more bytes until ``deadline`` (loop time)."""
        if self._closed_exc is not None:
            raise self._closed_exc
        if deadline - self.clock.monotonic() <= 0:
            raise LinkTimeout(self._timeout_message(wanted))
        waiter: asyncio.Future[None] = self._loop.create_future()
        self._waiter = waiter
        self._wait_until = deadline
        # One timer per link, re-armed only when it fires early: a timer per wait, cancelled
        # as soon as a byte comes, would pile up in the loop's heap with hundreds of links.
        if self._timer is None or self._timer.when() > deadline:
            if self._timer is not None:
                self._timer.cancel()
            self._timer = self.clock.call_at(deadline, self._on_timer)
        try:
            await waiter
        finally:
            self._waiter = None
        if self._closed_exc is not None and not self._buf:
            raise self._closed_exc

    def _on_timer(self) -> None:
        self._timer = None
        waiter = self._waiter
        if waiter is None or waiter.done():
            return
        if self.clock.monotonic() >= self._wait_until:
            waiter.set_result(None)
        else:
            self._timer = self.clock.call_at(self._wait_until, self._on_timer)

    def _timeout_message(self, wanted: str) -> str:
        got = f"; had received {format_raw(bytes(self._buf))}" if self._buf else ""
        return f"{self.url}: no answer in time (waiting for {wanted}){got}"

    def _deadline(self, timeout: float) -> float:
        if timeout < 0:
            raise UsageError(f"timeout must not be negative, not {timeout}")
        return self.clock.monotonic() + timeout

    async def read(self, max_bytes: int = 4096, *, timeout: float) -> bytes:
        """Return 1 to ``max_bytes`` bytes, waiting at most ``timeout`` s for the first."""
        if timeout < 0:
            raise UsageError(f"timeout must not be negative, not {timeout}")
        buf = self._buf
        if not buf:
            deadline = self.clock.monotonic() + timeout
            while not buf:
                await self._wait(deadline, "data")
        if len(buf) <= max_bytes:
            data = bytes(buf)
            buf.clear()
            return data
        data = bytes(buf[:max_bytes])
        del buf[:max_bytes]
        return data

    async def read_exactly(self, n: int, *, timeout: float) -> bytes:
        """Return exactly ``n`` bytes, all of them within ``timeout`` s."""
        deadline = self._deadline(timeout)
        while len(self._buf) < n:
            await self._wait(deadline, f"{n} bytes")
        data = bytes(self._buf[:n])
        del self._buf[:n]
        return data

    async def read_until(self, terminator: bytes, *, timeout: float) -> bytes:
        """Return everything up to and including ``terminator``, within ``timeout`` s."""
        deadline = self._deadline(timeout)
        start = 0
        while True:
            i = self._buf.find(terminator, start)
            if i >= 0:
                end = i + len(terminator)
                data = bytes(self._buf[:end])
                del self._buf[:end]
                return data
            start = max(0, len(self._buf) - len(terminator) + 1)
            await self._wait(deadline, f"{terminator!r}")

    def check_open(self) -> None:
        """Raise the link's LinkClosed (in its cause's words) if it is closed, from either end.

        Call it before answering from what this side keeps (the last CTS a server reported,
        an in-band readiness level): a line that is gone must not report its last level.
        """
        if self._closed_exc is not None:
            raise self._closed_exc

    def pending(self) -> bytes:
        """Bytes received but not read yet (left in place)."""
        return bytes(self._buf)

    def reset_input(self) -> bytes:
        """Discard (and return) bytes received but not read yet."""
        if not self._buf:
            return b""
        data = bytes(self._buf)
        self._buf.clear()
        return data

    async def cts(self) -> bool:
        """The host's CTS line (the machine's RTS). Only where ``has_modem_lines``."""
        raise UsageError(
            f"{self.url} cannot carry modem lines (CTS): use a serial port or rfc2217:// "
            "for a machine that signals readiness on RTS/CTS"
        )

    async def wait_cts(self, level: bool, *, timeout: float) -> None:
        """Wait until CTS is ``level``; raises LinkTimeout after ``timeout`` s."""
        deadline = self._deadline(timeout)
        while await self.cts() != level:
            await self._wait_modem(deadline, level)

    async def _wait_modem(self, deadline: float, level: bool) -> None:
        # Links that can see modem changes as events override this; polling is the fallback.
        if self.clock.monotonic() >= deadline:
            raise LinkTimeout(f"{self.url}: CTS did not go {'high' if level else 'low'} in time")
        await self.clock.sleep(min(0.01, max(0.0, deadline - self.clock.monotonic())))

    async def close(self) -> None:
        """Close the link; further reads and writes raise LinkClosed."""
        if self._closed_exc is None:
            self._closed_exc = LinkClosed(f"{self.url}: link closed")
        self._wake()
        await self._shutdown()

    async def __aenter__(self) -> Link:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url} {self.settings}>"
