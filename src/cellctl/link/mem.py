"""``mem://NAME``: a serial line inside one event loop, between a driver and an emulator.

No file descriptor, no thread: bytes go from one end to the other through the loop, each
character taking the line's time (start bit, data bits, parity, stop bits at the baud rate,
from :class:`LineSettings`) on the :class:`~cellctl.clock.Clock`, so a run on a virtual-time
loop takes the virtual time a real line would. Modem lines travel with no delay, as on a real
cable: the device's RTS and DTR are the host's CTS and DSR, the host's RTS and DTR the
device's CTS and DSR.

A device end listens under a name; a driver opens it like any link::

    listener = listen_mem("robot1", ROBOT_LINE, on_connect)   # on_connect(port: MemPort)
    link = await open_link("mem://robot1", ROBOT_LINE)

(``cellctl.emulators.memserve.serve_mem`` does the listening for an emulator.) Names live
per event loop. One host at a time, as on a serial port: a second open while one is open
is refused with :class:`~cellctl.errors.MachineInUse`. A host that opens with other framing
than the device's (baud, data bits, parity, stop bits) is refused before a byte goes out,
where a real line would garble every byte.

Pacing: each direction is a wire that carries one character per ``char_time``; a write
queues behind what is still crossing, and is handed over in slices of at most
:data:`PACE_SLICE_S` of line time, each when its last character has crossed (as a UART's
FIFO does; the emulators' serving slices the same way). ``pacing=False`` hands bytes over
on the next loop turn, in order.
"""

from __future__ import annotations

import asyncio
import re
import weakref
from collections import deque
from collections.abc import Callable

from cellctl.clock import Clock, current_clock
from cellctl.errors import LinkClosed, LinkError, LinkTimeout, MachineInUse, UsageError
from cellctl.link.base import Link
from cellctl.link.settings import LineSettings
from cellctl.link.trace import TrafficLog

#: The longest slice of line time handed over at once (seconds).
PACE_SLICE_S = 0.050

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
# A timer may fire a rounding error before its time (the loop's clock resolution).
_EPS = 1e-9


def _framing(settings: LineSettings) -> tuple[int, int, str, float]:
    return (settings.baudrate, settings.bytesize, settings.parity, settings.stopbits)


class _Lane:
    """One direction of the line: characters cross one per ``char_time``, in order."""

    def __init__(
        self,
        wire: MemWire,
        deliver: Callable[[bytes], None],
        closed: Callable[[], None],
    ) -> None:
        self._wire = wire
        self._deliver = deliver
        self._closed = closed
        # (through at, slice), oldest first; a slice of None: the far end closes then.
        self._queue: deque[tuple[float, bytes | None]] = deque()
        self._busy_until = float("-inf")  # when the last queued character is through
        self._timer: asyncio.TimerHandle | None = None

    def send(self, data: bytes) -> None:
        clock = self._wire.clock
        now = clock.monotonic()
        if not self._wire.pacing:
            self._queue.append((now, data))
        else:
            char_time = self._wire.settings.char_time
            step = max(1, int(PACE_SLICE_S / char_time))
            through = max(now, self._busy_until)
            for i in range(0, len(data), step):
                piece = data[i : i + step]
                through += len(piece) * char_time
                self._queue.append((through, piece))
            self._busy_until = through
        self._arm()

    def close_after(self) -> None:
        """The sending end closed: the far end hears it once the bytes before are through."""
        self._queue.append((max(self._wire.clock.monotonic(), self._busy_until), None))
        self._arm()

    def cut(self) -> None:
        """Drop what is still on the wire (a pulled cable)."""
        self._queue.clear()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _arm(self) -> None:
        if self._timer is None and self._queue:
            self._timer = self._wire.clock.call_at(self._queue[0][0], self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        now = self._wire.clock.monotonic()
        queue = self._queue
        # Everything through by now goes in one hand-over (one wake-up on the far end).
        due = bytearray()
        close = False
        while queue and queue[0][0] <= now + _EPS:
            piece = queue.popleft()[1]
            if piece is None:
                close = True
                queue.clear()
                break
            due += piece
        if due:
            self._deliver(bytes(due))
        if close:
            self._closed()
            return
        self._arm()


class MemPort:
    """The device's end of a :class:`MemWire` (what an emulator's line is built on).

    Set ``on_data`` (bytes from the host, once through the line) and ``on_closed`` (the host
    went away) before the first byte; ``write`` sends to the host, paced.
    """

    def __init__(self, wire: MemWire) -> None:
        self._wire = wire
        self.on_data: Callable[[bytes], None] = lambda data: None
        self.on_closed: Callable[[], None] = lambda: None

    @property
    def settings(self) -> LineSettings:
        return self._wire.settings

    @property
    def closed(self) -> bool:
        return self._wire.closed

    def write(self, data: bytes) -> None:
        """Send ``data`` to the host (nothing happens once the line is closed)."""
        wire = self._wire
        if data and not wire.closed and not wire.host_closed:
            wire.to_host.send(bytes(data))

    def set_rts(self, level: bool) -> None:
        """The device's RTS: the host's CTS."""
        self._wire._set_modem("device_rts", level)

    def set_dtr(self, level: bool) -> None:
        """The device's DTR: the host's DSR."""
        self._wire._set_modem("device_dtr", level)

    @property
    def cts(self) -> bool:
        """The device's CTS: the host's RTS."""
        return self._wire.host_rts

    @property
    def dsr(self) -> bool:
        """The device's DSR: the host's DTR."""
        return self._wire.host_dtr

    def close(self) -> None:
        """End the connection once what was written is through (as a server closes)."""
        self._wire._device_closes(abrupt=False)

    def drop(self) -> None:
        """Cut the connection now, bytes in flight lost (a pulled cable, a crashed server)."""
        self._wire._device_closes(abrupt=True)


class MemWire:
    """One connection of a ``mem://`` line: a host end (:class:`MemLink`) and a device end
    (:class:`MemPort`), paced on ``clock`` at ``settings``' rate."""

    def __init__(
        self, settings: LineSettings, *, clock: Clock | None = None, pacing: bool = True
    ) -> None:
        self.settings = settings
        self.clock = clock or current_clock()
        self.pacing = pacing
        self.closed = False
        self.host_closed = False  # the host closed its end (bytes may still be crossing)
        # A host port opened asserts DTR and RTS; a device's lines start low until it says.
        self.host_rts = True
        self.host_dtr = True
        self.device_rts = False
        self.device_dtr = False
        self.host: MemLink | None = None
        self.device = MemPort(self)
        self.to_device = _Lane(self, self._to_device, self._host_gone)
        self.to_host = _Lane(self, self._to_host, self._device_gone)

    def _to_device(self, data: bytes) -> None:
        self.device.on_data(data)

    def _to_host(self, data: bytes) -> None:
        if self.host is not None:
            self.host._feed(data)

    def _set_modem(self, which: str, level: bool) -> None:
        if self.closed or getattr(self, which) == level:
            return
        setattr(self, which, level)
        if self.host is not None:
            self.host._modem_changed()

    def _host_gone(self) -> None:
        self.closed = True
        self.device.on_closed()

    def _device_gone(self) -> None:
        self.closed = True
        if self.host is not None:
            self.host._feed_closed(LinkClosed(f"{self.host.url}: the other end closed the link"))

    def _host_closes(self) -> None:
        self.host_closed = True
        self.to_host.cut()  # a closed port hears nothing more
        if not self.closed:
            self.to_device.close_after()

    def _device_closes(self, *, abrupt: bool) -> None:
        if self.closed:
            return
        if abrupt:
            self.to_host.cut()
            self.to_device.cut()
            self._device_gone()
            self.device.on_closed()
        else:
            self.to_host.close_after()


class MemLink(Link):
    """The host's end of a ``mem://`` line (open it with ``open_link("mem://NAME")``)."""

    has_modem_lines = True

    def __init__(
        self,
        url: str,
        settings: LineSettings,
        trace: TrafficLog | None,
        label: str,
        wire: MemWire,
        clock: Clock | None = None,
    ) -> None:
        # Its deadlines on the clock the host gave, else the line's (which paces the bytes).
        super().__init__(url, settings, trace, label, clock=clock or wire.clock)
        self.wire = wire
        wire.host = self
        self._modem_waiter: asyncio.Future[None] | None = None

    async def _send(self, data: bytes) -> None:
        self.wire.to_device.send(data)

    async def _shutdown(self) -> None:
        self.wire._host_closes()

    def _feed_closed(self, exc: LinkError | None = None) -> None:
        super()._feed_closed(exc)
        self._modem_changed()

    async def cts(self) -> bool:
        """The host's CTS: the device's RTS (LinkClosed once the line is closed)."""
        self.check_open()
        return self.wire.device_rts

    async def dsr(self) -> bool:
        """The host's DSR: the device's DTR."""
        return self.wire.device_dtr

    def set_rts(self, level: bool) -> None:
        """The host's RTS (the device's CTS); high from the open on."""
        self.wire._set_modem("host_rts", level)

    def set_dtr(self, level: bool) -> None:
        """The host's DTR (the device's DSR); high from the open on."""
        self.wire._set_modem("host_dtr", level)

    def _modem_changed(self) -> None:
        waiter = self._modem_waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def _wait_modem(self, deadline: float, level: bool) -> None:
        # Modem changes are events here: wait for one (or the deadline), no polling.
        if self.closed:
            raise self._closed_exc or LinkClosed(f"{self.url}: link closed")
        clock = self.wire.clock
        left = deadline - clock.monotonic()
        if left <= 0:
            raise LinkTimeout(f"{self.url}: CTS did not go {'high' if level else 'low'} in time")
        waiter: asyncio.Future[None] = self._loop.create_future()
        self._modem_waiter = waiter
        try:
            async with clock.timeout(left):
                await waiter
        except TimeoutError:
            pass
        finally:
            self._modem_waiter = None


class MemListener:
    """A device end listening at ``mem://NAME`` in one event loop; ``close()`` stops it."""

    def __init__(
        self,
        name: str,
        settings: LineSettings,
        on_connect: Callable[[MemPort], None],
        *,
        clock: Clock | None,
        pacing: bool,
    ) -> None:
        self.name = name
        self.url = f"mem://{name}"
        self.settings = settings
        self.clock = clock
        self.pacing = pacing
        self.current: MemWire | None = None
        self._on_connect = on_connect
        self._loop = asyncio.get_running_loop()
        self.closed = False

    def connect(
        self,
        settings: LineSettings,
        trace: TrafficLog | None,
        label: str,
        clock: Clock | None = None,
    ) -> MemLink:
        """A host opens the line (what ``open_link`` calls)."""
        current = self.current
        if current is not None and not current.closed and not current.host_closed:
            raise MachineInUse(f"{self.url} is in use: another link holds it")
        if _framing(settings) != _framing(self.settings):
            raise UsageError(
                f"{self.url}: the machine's line is {self.settings}, the link asks for "
                f"{settings}: on a real line every byte would garble"
            )
        wire = MemWire(self.settings, clock=self.clock, pacing=self.pacing)
        link = MemLink(self.url, settings, trace, label, wire, clock)
        self.current = wire
        self._on_connect(wire.device)
        return link

    def close(self) -> None:
        """Stop listening and cut the current connection."""
        if self.closed:
            return
        self.closed = True
        endpoints = _endpoints.get(self._loop, {})
        if endpoints.get(self.name) is self:
            del endpoints[self.name]
        if self.current is not None:
            self.current.device.drop()


_endpoints: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, dict[str, MemListener]] = (
    weakref.WeakKeyDictionary()
)


def mem_name(url: str) -> str:
    """``"mem://robot1"`` → ``"robot1"``; refuses a URL that is not a plain ``mem://NAME``."""
    scheme, sep, name = url.partition("://")
    if scheme != "mem" or not sep or not name:
        raise UsageError(f"{url!r}: write mem://NAME")
    if not _NAME.fullmatch(name):
        raise UsageError(
            f"{url!r}: a mem:// name is letters, digits, '.', '_' and '-' (at most 128)"
        )
    return name


def listen_mem(
    name: str,
    settings: LineSettings,
    on_connect: Callable[[MemPort], None],
    *,
    clock: Clock | None = None,
    pacing: bool = True,
) -> MemListener:
    """Listen at ``mem://name`` in the running loop; ``on_connect(port)`` for each host.

    Raises UsageError for a bad name or one already listening in this loop.
    """
    mem_name(f"mem://{name}")
    endpoints = _endpoints.setdefault(asyncio.get_running_loop(), {})
    if name in endpoints:
        raise UsageError(f"mem://{name} is already listening in this event loop")
    listener = MemListener(name, settings, on_connect, clock=clock, pacing=pacing)
    endpoints[name] = listener
    return listener


def listening() -> list[str]:
    """The ``mem://`` URLs listening in the running loop."""
    return [f"mem://{name}" for name in _endpoints.get(asyncio.get_running_loop(), {})]


def open_mem(
    url: str,
    settings: LineSettings,
    trace: TrafficLog | None,
    label: str,
    clock: Clock | None = None,
) -> MemLink:
    """Open ``mem://NAME`` (``open_link`` does this): LinkError if nothing listens there."""
    name = mem_name(url)
    listener = _endpoints.get(asyncio.get_running_loop(), {}).get(name)
    if listener is None:
        raise LinkError(
            f"cannot connect to {url}: nothing listens there in this event loop "
            "(serve an emulator on it first: cellctl.emulators.memserve.serve_mem)"
        )
    return listener.connect(settings, trace, label, clock)


__all__ = [
    "PACE_SLICE_S",
    "MemLink",
    "MemListener",
    "MemPort",
    "MemWire",
    "listen_mem",
    "listening",
    "mem_name",
    "open_mem",
]
