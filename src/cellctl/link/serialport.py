"""Local serial devices and ptys, read through the event loop (epoll), not select().

pyserial opens and configures the port (baud, framing, RTS/CTS, ``xonxoff=False`` always:
Xon, Xoff and Ack are protocol bytes here); the bytes then move with ``os.read``/``os.write``
on the non-blocking descriptor from loop callbacks. pyserial's own ``read`` uses select(),
which fails for descriptors >= 1024; the event loop's epoll has no such limit, so one process
can hold thousands of links.
"""

from __future__ import annotations

import asyncio
import errno
import fcntl
import os
import resource
import stat
import struct
import termios

import serial

from cellctl.clock import Clock
from cellctl.errors import LinkClosed, LinkError, MachineInUse
from cellctl.link.base import Link
from cellctl.link.settings import LineSettings
from cellctl.link.trace import TrafficLog

_TIOCM_CTS = getattr(termios, "TIOCM_CTS", 0x020)

_STOPBITS = {1: serial.STOPBITS_ONE, 1.5: serial.STOPBITS_ONE_POINT_FIVE, 2: serial.STOPBITS_TWO}
_BYTESIZE = {5: serial.FIVEBITS, 6: serial.SIXBITS, 7: serial.SEVENBITS, 8: serial.EIGHTBITS}


def raise_fd_limit() -> int:
    """Raise this process's open-file limit to the hard limit; return the new soft limit.

    Each local serial link holds a few descriptors; the default soft limit (often 1024)
    would cap a controller at a few hundred machines.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 16)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    return soft


def is_pty(path: str) -> bool:
    """True for a pseudo-terminal slave (Unix98 ptys: major device numbers 136-143)."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    return stat.S_ISCHR(st.st_mode) and 136 <= os.major(st.st_rdev) <= 143


def open_pyserial(path: str, settings: LineSettings) -> serial.Serial:
    """Open ``path`` with ``settings`` through pyserial (Xon/Xoff in the OS always off)."""
    return serial.Serial(
        path,
        baudrate=settings.baudrate,
        bytesize=_BYTESIZE[settings.bytesize],
        parity=settings.parity,
        stopbits=_STOPBITS[settings.stopbits],
        rtscts=settings.rtscts,
        xonxoff=False,  # Xon, Xoff and Ack are protocol bytes: the codec must see them
        timeout=0,
        # flock on the device: a second opener (another cellctl, minicom -o, ...) is refused.
        # It works on a pty slave too: the emulator holds the slave open but never locks it.
        exclusive=True,
    )


class SerialLink(Link):
    """A serial device or pty, opened by path."""

    def __init__(
        self,
        path: str,
        settings: LineSettings,
        trace: TrafficLog | None,
        label: str,
        *,
        clock: Clock | None = None,
    ):
        super().__init__(path, settings, trace, label, clock=clock)
        framing = settings
        pty = is_pty(path)
        if pty:
            # A pty has no framing: Linux forces CS8 without parity on it and then refuses
            # 7E2 with EINVAL. The settings still govern pacing; only the termios differ.
            framing = settings.with_(bytesize=8, parity="N")
        try:
            self._port = open_pyserial(path, framing)
        except (serial.SerialException, OSError, ValueError, OverflowError) as e:
            # EAGAIN: another opener holds the device's flock; EBUSY: another program set
            # TIOCEXCL on it (or the driver allows one open).
            if getattr(e, "errno", None) in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY):
                raise MachineInUse(
                    f"{path} is in use: another program holds the device exclusively"
                ) from None
            # pyserial's own words repeat the path and the errno: the system's words alone.
            code = getattr(e, "errno", None)
            why = os.strerror(code).lower() if isinstance(code, int) else str(e)
            raise LinkError(f"cannot open serial port {path}: {why}") from e
        fd = self._port.fd
        assert fd is not None
        self._fd: int = fd
        # TIOCEXCL also refuses programs that take no flock (cat, screen) until we close. Not
        # on a pty: the emulator keeps the slave open, so the flag would outlive our close
        # and refuse our own reopen after a dropped link (the flock above covers ptys).
        self._tiocexcl = not pty and _set_exclusive(self._fd, termios.TIOCEXCL)
        # pyserial leaves the descriptor non-blocking; make sure, since we read it directly.
        flags = fcntl.fcntl(self._fd, fcntl.F_GETFL)
        fcntl.fcntl(self._fd, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self.has_modem_lines = self._probe_modem_lines()
        self._write_ready: asyncio.Future[None] | None = None
        self._loop.add_reader(self._fd, self._on_readable)

    def _probe_modem_lines(self) -> bool:
        # A pty has no modem lines: TIOCMGET fails there and works on a real UART.
        try:
            fcntl.ioctl(self._fd, termios.TIOCMGET, struct.pack("I", 0))
        except OSError:
            return False
        return True

    def _on_readable(self) -> None:
        while True:
            try:
                data = os.read(self._fd, 65536)
            except BlockingIOError:
                return
            except OSError as e:
                # EIO: the other side of a pty closed; anything else: the device went away.
                self._stop_reading()
                why = "the other end closed" if e.errno == errno.EIO else str(e)
                self._feed_closed(LinkClosed(f"{self.url}: {why}"))
                return
            if not data:
                self._stop_reading()
                self._feed_closed()
                return
            self._feed(data)
            if len(data) < 65536:
                return

    def _stop_reading(self) -> None:
        if self._fd >= 0:
            self._loop.remove_reader(self._fd)

    async def _send(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._fd, view)
            except BlockingIOError:
                n = 0
            except OSError as e:
                self._feed_closed(LinkClosed(f"{self.url}: write failed: {e}"))
                raise self._closed_exc or LinkClosed(str(e)) from e
            view = view[n:]
            if view:
                await self._writable()

    async def _writable(self) -> None:
        fut: asyncio.Future[None] = self._loop.create_future()
        self._loop.add_writer(self._fd, _resolve, fut)
        try:
            await fut
        finally:
            self._loop.remove_writer(self._fd)

    async def cts(self) -> bool:
        """The CTS input (the machine's RTS), read from the port."""
        if not self.has_modem_lines:
            return await super().cts()
        try:
            raw = fcntl.ioctl(self._fd, termios.TIOCMGET, struct.pack("I", 0))
        except OSError as e:
            raise LinkError(f"{self.url}: cannot read CTS: {e}") from e
        return bool(struct.unpack("I", raw)[0] & _TIOCM_CTS)

    async def _shutdown(self) -> None:
        if self._fd >= 0:
            self._stop_reading()
            if self._tiocexcl:
                _set_exclusive(self._fd, termios.TIOCNXCL)
            self._fd = -1
            self._port.close()


def _set_exclusive(fd: int, request: int) -> bool:
    """TIOCEXCL / TIOCNXCL on ``fd``; False where the device does not take it."""
    try:
        fcntl.ioctl(fd, request)
    except OSError:
        return False
    return True


def _resolve(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)
