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
import grp
import os
import pwd
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


def access_advice(path: str) -> str:
    """What a user refused a serial device can do about it, in the words of its group.

    Serial ports belong to a group (``dialout`` on Debian, ``uucp`` elsewhere) whose members
    may open them; a user added to it has it only from the next login on.
    """
    try:
        st = os.stat(path)
    except OSError:
        return "this user may not open it"
    try:
        group = grp.getgrgid(st.st_gid)
        name, members = group.gr_name, group.gr_mem
    except KeyError:
        name, members = str(st.st_gid), []
    mode = stat.filemode(st.st_mode)
    if st.st_mode & 0o060 != 0o060 or st.st_gid in (os.getegid(), *os.getgroups()):
        return f"its mode {mode} (group {name}) gives this user no access"
    user = _user_name()
    if user in members:
        return (
            f"you are in group {name}, but not in this login yet: log out and in again "
            f"(or `newgrp {name}`)"
        )
    return f"add yourself to its group {name} (`sudo usermod -aG {name} {user}`), then log in again"


def _not_a_device(path: str, error: BaseException) -> str | None:
    """What ``path`` is when it exists and is no serial device ("a regular file", "a
    directory", a device that is no terminal: ``error`` came of its line settings); None
    otherwise."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISCHR(mode):
        cause: BaseException | None = error
        while cause is not None:  # pyserial raises its own error while handling termios's
            if isinstance(cause, termios.error) and cause.args[:1] == (errno.ENOTTY,):
                return "a device that takes no line settings"
            cause = cause.__context__
        return None
    if stat.S_ISDIR(mode):
        return "a directory"
    return "a regular file" if stat.S_ISREG(mode) else "no character device"


def _user_name() -> str:
    try:
        return pwd.getpwuid(os.geteuid()).pw_name
    except KeyError:
        return str(os.geteuid())


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
                    f"{path} is in use: another program holds the device exclusively (a "
                    f"terminal program, another user's cellctl): end it; `fuser -v {path}` "
                    "names it"
                ) from None
            # pyserial's own words repeat the path and the errno: the system's words alone.
            code = getattr(e, "errno", None)
            why = os.strerror(code).lower() if isinstance(code, int) else str(e)
            if code in (errno.EACCES, errno.EPERM):
                why += f": {access_advice(path)}"
            elif (kind := _not_a_device(path, e)) is not None:
                # pyserial's words for a file are termios's: "Inappropriate ioctl for device".
                why = f"it is {kind}, not a serial device (a USB adapter is /dev/ttyUSB0 or "
                why += "/dev/serial/by-id/...)"
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
        self.check_open()  # a device that went away (EIO) must not be read as a level
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
