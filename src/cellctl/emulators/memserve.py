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
"""

from __future__ import annotations

import asyncio
import itertools
import weakref

from cellctl.clock import Clock, check_loop_clock
from cellctl.emulators.serve import DeviceLine, EmulatedDevice, Server, _run_session, _spawn
from cellctl.link import LineSettings
from cellctl.link.mem import MemPort, listen_mem

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
    server = Server(url=f"mem://{listen_name}", device=device)

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


__all__ = ["serve_mem"]
