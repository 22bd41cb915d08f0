"""Serve an emulated machine over a pty, raw TCP or RFC 2217, with the line paced.

An emulator implements :class:`EmulatedDevice` (one method, ``session``) and talks to the
host through a :class:`DeviceLine`; this module does the rest::

    server = await serve(MyEmulator(), "rfc2217://127.0.0.1:0", ROBOT_LINE)
    print(server.url)            # rfc2217://127.0.0.1:40123, what a driver passes to open_link
    ...
    await server.close()

``listen`` is ``"pty"`` (a new pseudo-terminal; ``"pty:/some/path"`` also keeps a symlink
there, re-pointed when a dropped connection makes a new pty), ``"socket://HOST:PORT"`` or
``"rfc2217://HOST:PORT"`` (port 0 picks a free one). One owner per ``pty:PATH``: the emulator
holds PATH's lock while it runs (a second one is refused with MachineInUse, naming it), never
replaces anything at PATH but a link (a file or a directory there is a UsageError), and on
close removes PATH only if it still points to its own pty.

Over RFC 2217 the emulator's RTS reaches the host as CTS, and line settings the host sets
change the pacing; a pty or raw TCP carries no modem lines. One host at a time: a new TCP
connection replaces the previous one, as a device server does when a controller restarts and
reconnects.

Pacing: with ``pacing=True`` (the default) the emulator receives each host byte no sooner than
it would have crossed the wire at the line's rate, and its own bytes reach the host at that
rate too, so timings match the real line. ``pacing=False`` moves bytes as fast as they come.

The line itself, paced and with its :class:`LineNoise` (the ``noise=RATE[,SEED]`` fault), is
:mod:`cellctl.emulators.line`; ``DeviceLine`` and ``LineNoise`` are importable from here too.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import os
import secrets
import stat
import tty
from abc import ABC, abstractmethod
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

from serial import rfc2217

from cellctl.clock import Clock, current_clock, emulator_clock

# Re-exported: emulators and their transports import the line from here.
from cellctl.emulators.line import DeviceLine as DeviceLine
from cellctl.emulators.line import LineNoise as LineNoise
from cellctl.emulators.switches import parse_fault as parse_fault
from cellctl.errors import LinkClosed, UsageError
from cellctl.link import LineSettings, parse_host_port
from cellctl.link.lock import OwnerLock, runtime_dir
from cellctl.tasks import cancel_and_wait

log = logging.getLogger(__name__)

#: Default time scales, one per use (each command's --help says its own and why):
#: a single machine's emulator runs in the machine's own time, so a driver, the console or
#: a stopwatch sees its real timing; an emulated cell or factory runs 50 times faster, so a
#: part's cuts take seconds and a batch minutes; the demo runs 200 times faster, so its batch
#: ends in about a minute. A driver told a scale (a mill's ``time_scale`` option, written by
#: ``emulate cell``) divides its estimates by it.
MACHINE_TIME_SCALE = 1.0
CELL_TIME_SCALE = 50.0
DEMO_TIME_SCALE = 200.0
#: What each command's --time-scale help adds, naming the others.
TIME_SCALE_HELP = (
    "Defaults: 1 for one machine's emulator (its real timing), 50 for `emulate cell` and "
    "`emulate factory` (a batch in minutes), 200 for `demo` (about a minute)."
)


#: The shortest deadline an emulated cell writes, s: the controller runs in wall time, and a
#: deadline scaled below this would tell a busy host as a fault.
MIN_DEADLINE_S = 5.0


def scaled_deadline(real_s: float, time_scale: float) -> float:
    """A deadline of the real cell (``real_s``) for machines ``time_scale`` times faster."""
    return max(MIN_DEADLINE_S, real_s / time_scale)


def _done(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


class EmulatedDevice(ABC):
    """A machine emulator: its state lives on the object and survives reconnects."""

    #: Line noise on every connection (the ``noise`` fault), or None.
    noise: LineNoise | None = None
    #: The clock given (see ``clock``); None: the running loop's, resolved when used.
    _clock: Clock | None = None

    @property
    def clock(self) -> Clock:
        """What the emulator times its machine on: the clock it was given, else the running
        loop's (an emulator may be made before its loop runs)."""
        return self._clock or current_clock()

    @property
    def time_scale(self) -> float:
        """Seconds of machine time per second of its clock: the emulator divides by it."""
        return self.clock.time_scale

    @time_scale.setter
    def time_scale(self, value: float) -> None:
        # Shorthand for the clock RealClock(value), as the constructors' time_scale=.
        self._clock = emulator_clock(None, value)

    @abstractmethod
    async def session(self, line: DeviceLine) -> None:
        """Serve one host connection until it closes (return, or let LinkClosed out)."""

    def line_changed(self, line: DeviceLine) -> None:  # noqa: B027 - optional hook
        """Called when the host changed the line settings (RFC 2217)."""

    async def operator_after(self, fault: str) -> None:  # noqa: B027 - optional hook
        """What the machine's operator does once fault switch ``fault`` went off, so the host
        can use the machine again (a panel's key, a pendant's unlock); the default: nothing.
        A plan's operator and the test rig call it after ``clear_fault``."""

    async def operator_clear(self) -> None:  # noqa: B027 - optional hook
        """What the operator does at the machine once its alarm was looked into: clear an
        error condition it keeps until someone does (the Dyna 2400's ERROR display). Called
        with no step of the machine's in flight; the default: nothing."""

    async def stop(self) -> None:  # noqa: B027 - optional hook
        """The emulator is shut down: end what the machine runs on its own (a program
        executing, its automatic operator). Serving ends with each server's ``close``; a
        machine goes on without its host, as a real one does, until this. The default:
        nothing runs on its own."""

    @property
    def moving(self) -> bool:
        """True while the machine's own program moves it (an operator waits for rest before
        taking a part out of a held transfer); the default: never."""
        return False

    async def listen(self, host: str) -> SelfServed | None:
        """Serve on ports of its own (a machine with several interfaces) and say how a
        cell reaches it; None (the default): :func:`serve` puts it on one line."""
        return None

    async def listen_mem(self, name: str, settings: LineSettings) -> SelfServed | None:
        """The same in the running event loop, on ``mem://`` names from ``name`` (a
        machine that serves itself: :func:`cellctl.emulators.memserve.serve_mem_streams`);
        None (the default): ``serve_mem`` puts it on one line."""
        return None


@dataclass
class SelfServed:
    """A device serving itself: ``url`` is what a driver opens, ``options`` what else the
    machine's options need to reach it (its other ports)."""

    url: str
    options: dict[str, int | float | str]
    closer: Callable[[], Coroutine[object, object, None]]
    current_line: DeviceLine | None = None

    async def close(self) -> None:
        await self.closer()


@dataclass
class Server:
    """A running emulator server: ``url`` is what a driver opens; ``close()`` stops it."""

    url: str
    device: EmulatedDevice
    name: str = ""
    """The machine it stands for, where the caller named it (its logs say so)."""
    _closers: list[Callable[[], None]] = field(default_factory=list)
    _tasks: set[asyncio.Task[None]] = field(default_factory=set)
    _stopped: asyncio.Event = field(default_factory=asyncio.Event)
    current_line: DeviceLine | None = None

    async def close(self) -> None:
        """Stop serving: close the connection and the listening endpoint."""
        for closer in reversed(self._closers):
            with contextlib.suppress(Exception):
                closer()
        await cancel_and_wait(self._tasks)
        self._stopped.set()

    async def serve_forever(self) -> None:
        """Wait until ``close()`` is called (or the task is cancelled)."""
        await self._stopped.wait()


async def _run_session(server: Server, line: DeviceLine, on_end: Callable[[], None]) -> None:
    server.current_line = line
    line.device = server.device
    try:
        await server.device.session(line)
    except LinkClosed:
        pass
    except Exception as e:  # the emulator's own bug: said with what it is, the line closed
        device = type(server.device)
        log.error(
            "emulator %s (%s.%s) failed in its session: %s: %s",
            server.name or server.url,
            device.__module__,
            device.__name__,
            type(e).__name__,
            e,
        )
    finally:
        line.feed_closed()
        on_end()


def _spawn(server: Server, coro: Coroutine[object, object, None]) -> asyncio.Task[None]:
    task = asyncio.ensure_future(coro)
    server._tasks.add(task)
    task.add_done_callback(server._tasks.discard)
    return task


async def serve(
    device: EmulatedDevice,
    listen: str,
    settings: LineSettings,
    *,
    pacing: bool = True,
    claimed: OwnerLock | None = None,
) -> Server:
    """Start serving ``device`` at ``listen``; see the module docstring. ``claimed``: the
    lock of a ``pty:PATH`` already taken (:func:`claim_pty_listen`); the server then holds
    it, and gives it back when it closes."""
    if listen == "pty" or listen.startswith("pty:"):
        return await _serve_pty(device, settings, pacing, listen, claimed)
    scheme = urlsplit(listen).scheme
    if scheme in ("socket", "tcp"):
        return await _serve_tcp(device, listen, settings, pacing, rfc=False)
    if scheme == "rfc2217":
        return await _serve_tcp(device, listen, settings, pacing, rfc=True)
    raise UsageError(
        f"cannot listen on {listen!r}: use pty, pty:PATH, socket://HOST:PORT or rfc2217://HOST:PORT"
    )


#: What a second emulator on a ``pty:PATH`` that a running one holds is told.
PTY_PATH_IN_USE = "{what} is served by {holder}: choose another path or stop that emulator"

#: What is at a path, in words, by its file type (a symlink is the one thing replaced).
_FILE_KINDS = (
    (stat.S_ISREG, "a regular file"),
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a named pipe"),
    (stat.S_ISSOCK, "a socket"),
)


def pty_link_path(text: str) -> Path:
    """The absolute path of ``pty:PATH``'s link: its directory resolved, its own name kept
    (a link already at PATH is what gets replaced, so it is never followed)."""
    path = Path(text)
    return Path(os.path.realpath(path.parent)) / path.name


def pty_lock_path(link: Path) -> Path:
    """The owner lock of the link ``link`` (absolute) in this user's runtime directory."""
    digest = hashlib.sha256(os.fsencode(link)).hexdigest()[:16]
    return runtime_dir() / f"pty-{digest}.lock"


def _refuse_other_than_link(listen: str, link: Path) -> None:
    """UsageError if something other than a symlink is at ``link``: it is the user's."""
    try:
        mode = os.lstat(link).st_mode
    except FileNotFoundError:
        return
    except OSError as e:
        raise UsageError(f"{listen}: cannot look at {link}: {e.strerror}") from None
    if stat.S_ISLNK(mode):
        return
    kind = next((name for test, name in _FILE_KINDS if test(mode)), "something")
    raise UsageError(
        f"{listen}: {kind} is there; the emulator makes PATH a link to its pty and will not "
        "replace it: choose another path or remove it"
    )


def claim_pty_listen(listen: str) -> OwnerLock | None:
    """Take ``listen``'s ``pty:PATH`` now, as :func:`serve` would, or refuse it: something not
    a link there (UsageError), or a running emulator's link (MachineInUse, naming it). None
    for any other ``listen``.

    A caller that writes files for the emulator takes it before it writes anything (two
    starts at once: one of them is refused before it touches the other's files), and hands
    it to ``serve(..., claimed=...)``; if it does not get there, it releases it."""
    if not listen.startswith("pty:") or listen == "pty:":
        return None
    return _claim_pty_link(listen, pty_link_path(listen[4:]))


def _claim_pty_link(listen: str, link: Path) -> OwnerLock:
    """PATH's lock for this emulator's life, once nothing of the user's is there."""
    _refuse_other_than_link(listen, link)
    # A link whose lock is free was left by an emulator that is gone: it is replaced.
    return OwnerLock.acquire(pty_lock_path(link), listen, refusal=PTY_PATH_IN_USE)


def _point_link(link: Path, target: str) -> None:
    """Make ``link`` a symlink to ``target`` in one step, never following a link there.

    The new link is made under a temporary name next to ``link`` (built from ``link``'s own
    name, not its target's) and renamed over it: rename replaces a symlink, not what it
    points to, and a reader never sees PATH missing."""
    tmp = link.with_name(f".{link.name}.{os.getpid()}-{secrets.token_hex(4)}.new")
    os.symlink(target, tmp)
    try:
        os.replace(tmp, link)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


async def _serve_pty(
    device: EmulatedDevice,
    settings: LineSettings,
    pacing: bool,
    listen: str,
    claimed: OwnerLock | None,
) -> Server:
    loop = asyncio.get_running_loop()
    given = listen[4:]
    link = pty_link_path(given) if given else None
    lock = claimed
    if lock is None and link is not None:
        lock = _claim_pty_link(listen, link)
    server = Server(url="", device=device)
    current = {"pty": ""}  # the pty the link points to now: what close may remove

    def open_pty() -> str:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/LF translation: bytes as they are
        os.set_blocking(master, False)
        name = os.ttyname(slave)
        fds = {"closed": False}

        def send(data: bytes) -> None:
            # The host side is a tty buffer of a few KiB; records are far smaller.
            with contextlib.suppress(BlockingIOError, OSError):
                os.write(master, data)

        def close_fds() -> None:
            if fds["closed"]:
                return
            fds["closed"] = True
            loop.remove_reader(master)
            os.close(master)
            # The emulator holds the slave too, so a host closing it doesn't EIO the master.
            os.close(slave)

        def on_drop() -> None:
            close_fds()
            # A dropped pty is gone for good, as an unplugged cable; a new one takes its place.
            loop.call_soon(repoint)

        line = DeviceLine(settings, pacing=pacing, send=send, on_drop=on_drop, clock=device.clock)
        line.device = device

        def readable() -> None:
            try:
                data = os.read(master, 65536)
            except BlockingIOError:
                return
            except OSError:
                data = b""
            if data:
                line.feed(data)

        loop.add_reader(master, readable)
        server._closers.append(close_fds)
        _spawn(server, _run_session(server, line, lambda: None))
        return name

    def repoint() -> None:
        if server._stopped.is_set():
            return
        name = open_pty()
        if link is None:
            server.url = name
            return
        # We hold PATH's lock, so no other emulator is there; but a file the user put at
        # PATH since is theirs, and a failure here must not stop the emulator serving.
        with contextlib.suppress(UsageError, OSError):
            _refuse_other_than_link(listen, link)
            _point_link(link, name)
            current["pty"] = name

    def remove_link() -> None:
        # Only our own link goes: a file put at PATH since, or a link re-made by someone
        # else, stays as it is.
        assert link is not None
        with contextlib.suppress(OSError):
            if os.readlink(link) == current["pty"]:
                os.unlink(link)

    if lock is not None:
        server._closers.append(lock.release)  # closers run last first: the lock goes last
        server._closers.append(remove_link)
    try:
        name = open_pty()
        if link is not None:
            try:
                _point_link(link, name)
            except OSError as e:
                raise UsageError(
                    f"{listen}: cannot make the link to the pty: {e.strerror}"
                ) from None
            current["pty"] = name
    except BaseException:
        await server.close()
        raise
    server.url = given if link is not None else name
    return server


class _VirtualPort:
    """The serial-port face pyserial's RFC 2217 PortManager expects, backed by a DeviceLine."""

    def __init__(self, settings: LineSettings, on_change: Callable[[LineSettings], None]):
        self._settings = settings
        self._on_change = on_change
        self.xonxoff = False
        self.dtr = True
        self.rts = True
        self.break_condition = False
        self.cts = False
        self.dsr = True
        self.ri = False
        self.cd = True

    def _set(self, **kw: object) -> None:
        try:
            self._settings = self._settings.with_(**kw)
        except UsageError as e:
            raise ValueError(str(e)) from e
        self._on_change(self._settings)

    @property
    def baudrate(self) -> int:
        return self._settings.baudrate

    @baudrate.setter
    def baudrate(self, v: int) -> None:
        self._set(baudrate=v)

    @property
    def bytesize(self) -> int:
        return self._settings.bytesize

    @bytesize.setter
    def bytesize(self, v: int) -> None:
        self._set(bytesize=v)

    @property
    def parity(self) -> str:
        return self._settings.parity

    @parity.setter
    def parity(self, v: str) -> None:
        self._set(parity=v)

    @property
    def stopbits(self) -> float:
        return self._settings.stopbits

    @stopbits.setter
    def stopbits(self, v: float) -> None:
        self._set(stopbits=v)

    @property
    def rtscts(self) -> bool:
        return self._settings.rtscts

    @rtscts.setter
    def rtscts(self, v: bool) -> None:
        self._set(rtscts=v)

    def reset_input_buffer(self) -> None:
        pass

    def reset_output_buffer(self) -> None:
        pass


#: Bytes taken from a host's socket per read: asyncio's own 256 KiB makes every read map a
#: fresh buffer, which a few thousand emulated lines in one process feel (see link.tcp).
_READ_SIZE = 4096


class _TcpConnection(asyncio.BufferedProtocol):
    def __init__(self, server: Server, settings: LineSettings, pacing: bool, rfc: bool):
        self._view = memoryview(bytearray(_READ_SIZE))
        self.server = server
        self.settings = settings
        self.pacing = pacing
        self.rfc = rfc
        self.transport: asyncio.Transport | None = None
        self.line: DeviceLine | None = None
        self.manager: rfc2217.PortManager | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            import socket

            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        previous = self.server.current_line
        if previous is not None and not previous.closed:
            previous.drop()  # one host at a time: the newest connection wins
        send: Callable[[bytes], None] = transport.write
        on_rts = None
        if self.rfc:
            port = _VirtualPort(self.settings, self._settings_changed)
            self.port = port
            # PortManager only needs attribute access and write(): duck-typed stand-ins.
            self.manager = rfc2217.PortManager(port, _Writer(transport))  # type: ignore[arg-type]
            mgr = self.manager

            def escaped_send(data: bytes) -> None:
                transport.write(b"".join(mgr.escape(data)))

            send = escaped_send

            def on_rts(level: bool) -> None:
                port.cts = level
                mgr.check_modem_lines()

        line = DeviceLine(
            self.settings,
            pacing=self.pacing,
            send=send,
            has_modem_lines=self.rfc,
            on_rts=on_rts,
            on_drop=transport.abort,
            clock=self.server.device.clock,
        )
        line.device = self.server.device
        self.line = line
        _spawn(self.server, _run_session(self.server, line, transport.close))

    def _settings_changed(self, settings: LineSettings) -> None:
        if self.line is not None:
            self.line.settings = settings
            self.server.device.line_changed(self.line)

    def get_buffer(self, sizehint: int) -> memoryview:
        return self._view

    def buffer_updated(self, nbytes: int) -> None:
        assert self.line is not None
        data = bytes(self._view[:nbytes])
        if self.manager is not None:
            data = b"".join(self.manager.filter(data))
        self.line.feed(data)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.line is not None:
            self.line.feed_closed()


class _Writer:
    def __init__(self, transport: asyncio.Transport) -> None:
        self.transport = transport

    def write(self, data: bytes) -> None:
        if not self.transport.is_closing():
            self.transport.write(data)


async def _serve_tcp(
    device: EmulatedDevice, listen: str, settings: LineSettings, pacing: bool, *, rfc: bool
) -> Server:
    host, port = parse_host_port(listen)
    loop = asyncio.get_running_loop()
    server = Server(url="", device=device)
    try:
        tcp = await loop.create_server(
            lambda: _TcpConnection(server, settings, pacing, rfc), host, port
        )
    except OSError as e:
        raise UsageError(f"cannot listen on {listen}: {e.strerror or e}") from e
    bound = tcp.sockets[0].getsockname()
    server.url = f"{'rfc2217' if rfc else 'socket'}://{host}:{bound[1]}"

    def close() -> None:
        tcp.close()
        line = server.current_line
        if line is not None and not line.closed:
            line.drop()

    server._closers.append(close)
    return server
