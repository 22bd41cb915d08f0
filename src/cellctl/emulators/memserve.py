"""Serve an emulated machine on ``mem://NAME``: in the same event loop as its driver.

The in-process counterpart of :func:`cellctl.emulators.serve.serve`: the emulator's session
runs on a :class:`DeviceLine` as over a pty or TCP, with the ``mem://`` line doing the pacing
(at the line's rate, on the loop's clock) and carrying the modem lines (the emulator's RTS is
the host's CTS)::

    server = await serve_mem(emulator, settings, name="cnc1")   # any EmulatedDevice
    link = await open_link(server.url, settings)                 # "mem://cnc1" (or a
    ...                                                          # driver's connect(server.url))
    await server.close()

On a virtual-time loop (:func:`cellctl.clock.run_virtual`) the pair runs byte for byte as over
a real line, each character taking its line time of virtual time.

A machine that serves network interfaces of its own (asyncio stream handlers, as for
``asyncio.start_server``) serves each on a ``mem://`` name with :func:`serve_mem_streams`::

    listener = serve_mem_streams("robot.rtde", settings, handler)  # handler(reader, writer)
"""

from __future__ import annotations

import asyncio
import itertools
import weakref
from collections.abc import Awaitable, Callable
from typing import Any

from cellctl.clock import Clock, check_loop_clock
from cellctl.emulators.serve import DeviceLine, EmulatedDevice, Server, _run_session, _spawn
from cellctl.link import LineSettings
from cellctl.link.mem import MemListener, MemPort, listen_mem

# Names made up per event loop when none is given: mem://<device class>-<n>.
_counters: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, itertools.count[int]] = (
    weakref.WeakKeyDictionary()
)


def _default_name(device: EmulatedDevice) -> str:
    counter = _counters.setdefault(asyncio.get_running_loop(), itertools.count(1))
    return f"{type(device).__name__.lower()}-{next(counter)}"


async def serve_mem(
    device: EmulatedDevice,
    settings: LineSettings,
    *,
    name: str | None = None,
    clock: Clock | None = None,
    pacing: bool = True,
) -> Server:
    """Serve ``device`` at ``mem://name`` (a fresh name if None) in the running loop.

    Each host that opens the URL gets a session of its own, as a TCP connection does; one
    host at a time (a second open is refused while one is open). ``pacing=False`` hands bytes
    over as fast as they come. ``server.close()`` stops listening and cuts the connection.
    """
    check_loop_clock(device.clock, f"{type(device).__name__}")
    listen_name = name or _default_name(device)
    server = Server(url=f"mem://{listen_name}", device=device, name=name or "")

    def on_connect(port: MemPort) -> None:
        # The wire paces both ways: the DeviceLine on top hands bytes through as they come.
        line = DeviceLine(
            settings,
            pacing=False,
            send=port.write,
            has_modem_lines=True,
            on_rts=port.set_rts,
            on_drop=port.drop,
            clock=device.clock,
        )
        line.device = device
        port.on_data = line.feed
        port.on_closed = line.feed_closed
        _spawn(server, _run_session(server, line, port.close))

    listener = listen_mem(listen_name, settings, on_connect, clock=clock, pacing=pacing)
    server._closers.append(listener.close)
    return server


class _PortTransport(asyncio.Transport):
    """A ``mem://`` device end as an asyncio transport: what a stream handler writes goes to
    the host; ``close`` ends once it is through, ``abort`` cuts (a dropped connection)."""

    def __init__(self, port: MemPort) -> None:
        super().__init__()
        self._port = port
        self._closing = False

    def write(self, data: Any) -> None:
        if not self.is_closing():
            self._port.write(bytes(data))

    def is_closing(self) -> bool:
        return self._closing or self._port.closed

    def close(self) -> None:
        if not self._closing:
            self._closing = True
            self._port.close()

    def abort(self) -> None:
        self._closing = True
        self._port.drop()

    def can_write_eof(self) -> bool:
        return False

    def get_write_buffer_size(self) -> int:
        return 0


StreamHandler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


def serve_mem_streams(
    name: str, settings: LineSettings, handler: StreamHandler, *, clock: Clock | None = None
) -> MemListener:
    """Serve ``handler(reader, writer)`` at ``mem://name`` in the running loop, for each host
    that opens it, as ``asyncio.start_server`` does on a port (unpaced: a network interface,
    not a serial line). A writer's ``drain`` raises ConnectionResetError once the host has
    gone, as over TCP; ``close()`` of the listener cuts the connection."""
    loop = asyncio.get_running_loop()
    tasks: set[asyncio.Task[None]] = set()

    def on_connect(port: MemPort) -> None:
        reader = asyncio.StreamReader()
        protocol = asyncio.StreamReaderProtocol(reader)
        transport = _PortTransport(port)
        protocol.connection_made(transport)
        port.on_data = protocol.data_received
        lost = False

        def gone() -> None:
            nonlocal lost
            if not lost:
                lost = True
                protocol.connection_lost(None)

        port.on_closed = gone
        writer = asyncio.StreamWriter(transport, protocol, reader, loop)
        task = asyncio.ensure_future(handler(reader, writer))
        tasks.add(task)
        task.add_done_callback(tasks.discard)

    return listen_mem(name, settings, on_connect, clock=clock, pacing=False)


__all__ = ["serve_mem", "serve_mem_streams"]
