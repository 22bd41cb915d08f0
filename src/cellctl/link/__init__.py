"""Link layer: bytes in and out of a machine, whatever carries them.

Open a link from a URL, as pyserial's ``serial_for_url`` does; drivers never know what is
underneath::

    from cellctl.link import open_link, LineSettings, TrafficLog

    link = await open_link("rfc2217://localhost:7001", LineSettings.parse("4800,7E2"),
                           trace=TrafficLog("mill1.trace"))
    await link.write(b"R")
    reply = await link.read(timeout=2.0)
    ready = await link.cts()          # serial ports and rfc2217:// only

URLs: a device path (``/dev/ttyUSB0``, a pty such as ``/dev/pts/7``; ``serial://`` prefix
optional), ``socket://host:port`` (raw TCP serial server), ``rfc2217://host:port`` (ser2net
in telnet/RFC 2217 mode, serial device servers: line settings and modem lines travel too),
``loop://`` (loopback), ``mem://NAME`` (an emulator in the same event loop, paced by the
clock at the line's rate, modem lines carried: :mod:`cellctl.link.mem`).
"""

from __future__ import annotations

from pathlib import Path
from urllib.parse import urlsplit

from cellctl.clock import Clock
from cellctl.errors import UsageError
from cellctl.link.base import Link
from cellctl.link.settings import ETHERNET_LINE, MILL_LINE, ROBOT_LINE, LineSettings
from cellctl.link.trace import RECEIVED, SENT, TrafficLog

__all__ = [
    "ETHERNET_LINE",
    "MILL_LINE",
    "RECEIVED",
    "ROBOT_LINE",
    "SENT",
    "LineSettings",
    "Link",
    "TrafficLog",
    "open_link",
    "parse_host_port",
]

_fd_limit_raised = False


def parse_host_port(url: str) -> tuple[str, int]:
    """``"socket://host:port"`` → ``("host", port)``; refuses a URL without a port."""
    parts = urlsplit(url)
    try:
        port = parts.port
    except ValueError as e:
        raise UsageError(f"{url}: bad port number") from e
    if not parts.hostname or port is None:
        raise UsageError(f"{url}: write {parts.scheme}://HOST:PORT")
    return parts.hostname, port


async def open_link(
    url: str,
    settings: LineSettings = ROBOT_LINE,
    *,
    trace: TrafficLog | str | Path | None = None,
    label: str | None = None,
    connect_timeout: float = 5.0,
    clock: Clock | None = None,
) -> Link:
    """Open the link ``url`` with ``settings``; ``trace`` logs every byte both ways.

    ``clock`` is what its deadlines and trace stamps read (None: the running loop's; for
    ``mem://``, the line's, which paces the bytes).

    Raises UsageError for a URL it does not understand and LinkError when the far end
    cannot be reached.
    """
    global _fd_limit_raised
    log = TrafficLog(trace) if isinstance(trace, str | Path) else trace
    name = label or url
    try:
        scheme = urlsplit(url).scheme if "://" in url else ""
    except ValueError as e:  # e.g. an unclosed "[" of an IPv6 address
        raise UsageError(f"link URL {url!r} not understood: {e}") from None
    if scheme in ("", "serial"):
        from cellctl.link.serialport import SerialLink, raise_fd_limit

        if not _fd_limit_raised:
            raise_fd_limit()
            _fd_limit_raised = True
        path = url.split("://", 1)[1] if scheme else url
        if not path:
            raise UsageError("empty serial device path")
        return SerialLink(path, settings, log, name, clock=clock)
    if scheme == "socket":
        from cellctl.link.tcp import TcpLink

        host, port = parse_host_port(url)
        tcp = TcpLink(url, settings, log, name, clock=clock)
        await tcp._connect(host, port, connect_timeout)
        return tcp
    if scheme == "rfc2217":
        from cellctl.link.rfc2217 import Rfc2217Link

        host, port = parse_host_port(url)
        link = Rfc2217Link(url, settings, log, name, clock=clock)
        await link._connect(host, port, connect_timeout)
        try:
            await link._negotiate(connect_timeout)
        except BaseException:
            await link.close()
            raise
        return link
    if scheme == "loop":
        from cellctl.link.loop import LoopLink

        return LoopLink(url, settings, log, name, clock=clock)
    if scheme == "mem":
        from cellctl.link.mem import open_mem

        return open_mem(url, settings, log, name, clock)
    raise UsageError(
        f"link URL {url!r} not understood: use a device path, socket://HOST:PORT, "
        "rfc2217://HOST:PORT, loop:// or mem://NAME"
    )
