"""A private Mosquitto broker for tests, ``cellctl emulate factory`` and ``cellctl demo --factory``.

::

    async with MosquittoBroker(tmp / "broker", [("cell1", "cellctl/cell1")]) as broker:
        broker.url                      # "mqtt://127.0.0.1:PORT"
        broker.credentials("cell1")     # a 0600 TOML file: username = "cell1", password = "..."
        broker.credentials("factory")
        await broker.restart()          # same port, persisted sessions and messages kept

    # Kept up: a broker that dies (killed, crashed) is said and started again, same port,
    # configuration and persistence, at most 3 times in a row before the watch gives up.
    MosquittoBroker(directory, cells, restarts=3, say=print)

The broker gets its own ``mosquitto.conf`` in ``directory``: the lines of
:func:`production_conf` (the configuration docs/factory.md gives for production) with the
directory's paths, a plain listener on ``host:port``, and a log file. With
``tls=TlsFiles(...)`` it also has a TLS listener on ``host:tls_port`` (``broker.tls_url``).
No anonymous clients, a password file made with ``mosquitto_passwd``, an ACL file,
persistence on (in ``directory/data``), and on every listener each user's client id is its
user name (``use_username_as_clientid``): one user cannot take another's
session, nor disconnect it by connecting with its client id. A cell user may read only
``PREFIX/orders`` and write only ``PREFIX/reports``, ``PREFIX/state`` and ``PREFIX/status``
of its own prefix; the factory user reads every configured prefix's reports, state and status
and writes every ``PREFIX/orders``: one explicit line per prefix, no wildcard over other prefixes.
Passwords are made once and kept in the credentials files, so a second broker over the same
directory accepts the same clients. It never touches a system service.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import pwd
import re
import secrets
import shutil
import signal
import socket
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Self

from cellctl.clock import current_clock
from cellctl.errors import CellctlError, LinkError, UsageError
from cellctl.mailbox.wire import MAX_PAYLOAD

#: Where Debian puts the broker and its password tool.
MOSQUITTO = "/usr/sbin/mosquitto"
MOSQUITTO_PASSWD = "/usr/bin/mosquitto_passwd"
#: The factory's user name in the broker.
FACTORY_USER = "factory"
#: The largest MQTT packet the broker takes, bytes: the largest payload the factory and the
#: cells read (:data:`~cellctl.mailbox.wire.MAX_PAYLOAD`) with room for its topic and header.
MAX_PACKET = MAX_PAYLOAD + 4096
#: How long start() waits for the broker to accept connections.
START_TIMEOUT_S = 10.0
#: How long stop() waits for the broker to exit after SIGTERM before killing it.
STOP_TIMEOUT_S = 10.0
#: Seconds between two attempts to start a broker that died (times the attempt's number).
RESTART_PAUSE_S = 0.5

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
_PREFIX = re.compile(r"[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*")


@dataclass(frozen=True)
class TlsFiles:
    """The broker's certificate chain and key (PEM) for its TLS listener."""

    certfile: Path
    keyfile: Path


#: Where the production broker's files are (docs/factory.md).
ETC = Path("/etc/mosquitto")
VAR = Path("/var/lib/mosquitto")


def global_lines(*, etc: Path = ETC, var: Path = VAR) -> list[str]:
    """The broker's options for every listener: passwords, ACLs, persistence."""
    # per_listener_settings comes first: Mosquitto reads it before any other option.
    return [
        "per_listener_settings false",
        "allow_anonymous false",
        f"password_file {etc / 'passwd'}",
        f"acl_file {etc / 'acl'}",
        "persistence true",
        f"persistence_location {var}/",
        # A message larger than any the factory or a cell reads (their MAX_PAYLOAD, and room
        # for the topic and header) is refused at the door: its sender is disconnected, and
        # nothing of it is held in memory, stored retained or replayed to the factory.
        f"max_packet_size {MAX_PACKET}",
    ]


def listener_lines(port: int, host: str, tls: TlsFiles | None) -> list[str]:
    """One listener; with ``tls``, one that speaks TLS only."""
    lines = [
        f"listener {port} {host}",
        # A client's id is its user name: nobody can take the factory's or a cell's session
        # (and disconnect it) by connecting with its client id. A listener's own option:
        # before any listener line it would open a second, default listener without it.
        "use_username_as_clientid true",
    ]
    if tls is not None:
        lines += [f"certfile {tls.certfile}", f"keyfile {tls.keyfile}", "tls_version tlsv1.2"]
    return lines


def production_conf() -> str:
    """The broker configuration docs/factory.md gives for production.

    The private broker runs the same lines (:func:`global_lines`, :func:`listener_lines`)
    with its own paths, so the tests check what the documentation says.
    """
    tls = TlsFiles(ETC / "certs" / "broker.crt", ETC / "certs" / "broker.key")
    return "\n".join([*global_lines(), *listener_lines(8883, "0.0.0.0", tls)]) + "\n"


def acl(cells: Sequence[tuple[str, str]]) -> str:
    """The ACL file: the factory writes each cell's orders and reads its reports, state and
    status; a cell reads its own orders and writes its own reports, state and status. One line
    per prefix, never a wildcard over other prefixes."""
    lines = [f"user {FACTORY_USER}"]
    for _, prefix in cells:
        lines += [
            f"topic write {prefix}/orders",
            f"topic read {prefix}/reports",
            f"topic read {prefix}/state",
            f"topic read {prefix}/status",
        ]
    for name, prefix in cells:
        lines += [
            "",
            f"user {name}",
            f"topic read {prefix}/orders",
            f"topic write {prefix}/reports",
            f"topic write {prefix}/state",
            f"topic write {prefix}/status",
        ]
    return "\n".join(lines) + "\n"


def _tool(path: str, name: str) -> str:
    if os.access(path, os.X_OK):
        return path
    found = shutil.which(name)
    if found is None:
        raise UsageError(
            f"{name} is not installed (looked for {path}): install Debian's mosquitto package"
        )
    return found


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        port: int = sock.getsockname()[1]
        return port


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` with mode 0600 from the first byte on."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    os.chmod(path, 0o600)


class MosquittoBroker:
    """A Mosquitto process with a generated configuration; see the module docstring."""

    def __init__(
        self,
        directory: Path,
        cells: Sequence[tuple[str, str]],
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        tls: TlsFiles | None = None,
        tls_port: int = 0,
        restarts: int = 0,
        say: Callable[[str], None] = lambda text: None,
    ) -> None:
        names = [name for name, _ in cells]
        for name, prefix in cells:
            if not _NAME.fullmatch(name) or name == FACTORY_USER:
                raise UsageError(f"cell name {name!r} cannot be a broker user name")
            if not _PREFIX.fullmatch(prefix):
                raise UsageError(
                    f"topic prefix {prefix!r} must be words joined by '/' (no wildcards)"
                )
        if len(set(names)) != len(names):
            raise UsageError("two cells have the same name")
        if len({p for _, p in cells}) != len(cells):
            raise UsageError("two cells have the same topic prefix")
        self.directory = Path(directory)
        self.cells = list(cells)
        self.host = host
        self.port = port
        self.tls = tls
        self.tls_port = tls_port
        #: Attempts in a row to start the broker again when it dies (0: not watched).
        self.restarts = restarts
        #: Where the watch says what happened to the broker, one line each.
        self.say = say
        #: Why the watch gave up (the broker died and would not start again), or None.
        self.failure: CellctlError | None = None
        self._process: asyncio.subprocess.Process | None = None
        self._meant_to_end = False  # stop() or kill() ended it: not a death to answer
        self._watch: asyncio.Task[None] | None = None
        self._restarting = False  # the watch is starting the broker again

    @property
    def url(self) -> str:
        """``mqtt://HOST:PORT`` (the port is known once started)."""
        return f"mqtt://{self.host}:{self.port}"

    @property
    def tls_url(self) -> str:
        """``mqtts://HOST:TLS_PORT`` (with ``tls``, once started)."""
        return f"mqtts://{self.host}:{self.tls_port}"

    @property
    def running(self) -> bool:
        """Whether the broker process is alive."""
        return self._process is not None and self._process.returncode is None

    @property
    def log_path(self) -> Path:
        """The broker's own log file."""
        return self.directory / "mosquitto.log"

    @property
    def stderr_path(self) -> Path:
        """What the broker last wrote on stderr (before its log file opens)."""
        return self.directory / "mosquitto.stderr"

    def credentials(self, user: str) -> Path:
        """The credentials file of ``user`` ("factory" or a cell name), made if missing."""
        if user != FACTORY_USER and user not in {name for name, _ in self.cells}:
            raise UsageError(f"no broker user {user!r} (known: factory and the cells' names)")
        self.directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        path = self.directory / f"{user}.credentials"
        if not path.exists():
            password = secrets.token_urlsafe(18)
            _write_private(path, f'username = "{user}"\npassword = "{password}"\n')
        return path

    def _password(self, user: str) -> str:
        data = tomllib.loads(self.credentials(user).read_text(encoding="utf-8"))
        return str(data["password"])

    async def _write_passwords(self, path: Path) -> None:
        tool = _tool(MOSQUITTO_PASSWD, "mosquitto_passwd")
        _write_private(path, "")
        for user in [FACTORY_USER, *(name for name, _ in self.cells)]:
            # -b takes the password on the command line: fine for a private, generated one.
            proc = await asyncio.create_subprocess_exec(
                tool,
                "-b",
                str(path),
                user,
                self._password(user),
                stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.STDOUT,
            )
            out, _ = await proc.communicate()
            if proc.returncode != 0:
                raise UsageError(f"mosquitto_passwd failed for {user}: {out.decode().strip()}")
        os.chmod(path, 0o600)

    async def _configure(self) -> Path:
        self.directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        data = self.directory / "data"
        data.mkdir(exist_ok=True, mode=0o700)
        await self._write_passwords(self.directory / "passwd")
        _write_private(self.directory / "acl", acl(self.cells))
        conf = self.directory / "mosquitto.conf"
        listeners = listener_lines(self.port, self.host, None)
        if self.tls is not None:
            listeners += listener_lines(self.tls_port, self.host, self.tls)
        _write_private(
            conf,
            "\n".join(
                [
                    "# Generated by cellctl.factory.broker: a private broker, loopback only.",
                    "# docs/factory.md's production configuration, with this directory's paths",
                    "# and its listeners on loopback (a plain one for tests and demos):",
                    *global_lines(etc=self.directory, var=data),
                    *listeners,
                    # Run as whoever started us: as root, Mosquitto would otherwise switch to
                    # the 'mosquitto' user, who cannot read these 0600 files.
                    f"user {pwd.getpwuid(os.getuid()).pw_name}",
                    # Saved each second too, so a broker killed -9 loses at most one second.
                    "autosave_interval 1",
                    f"log_dest file {self.log_path}",
                    "log_type error",
                    "log_type warning",
                    "log_type notice",
                    "log_type information",
                    "connection_messages true",
                    "log_timestamp true",
                    "",
                ]
            ),
        )
        return conf

    async def start(self) -> None:
        """Write the configuration, start Mosquitto and wait until it accepts connections;
        with ``restarts``, watch it from then on."""
        if self.running:
            return
        self._meant_to_end = False
        await self._launch()
        if self.restarts > 0 and (self._watch is None or self._watch.done()):
            self._watch = asyncio.create_task(self._keep_up(), name="mosquitto-watch")

    async def _launch(self) -> None:
        tool = _tool(MOSQUITTO, "mosquitto")
        if self.port == 0:
            self.port = _free_port(self.host)
        if self.tls is not None and self.tls_port == 0:
            self.tls_port = _free_port(self.host)
        conf = await self._configure()
        # What Mosquitto says before its log file is open (an unreadable persistence file,
        # a bad option) goes to its stderr: kept, for the error when it exits at start.
        fd = os.open(self.stderr_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            self._process = await asyncio.create_subprocess_exec(
                tool,
                "-c",
                str(conf),
                stdin=asyncio.subprocess.DEVNULL,
                stdout=asyncio.subprocess.DEVNULL,
                stderr=fd,
                start_new_session=True,  # a Ctrl-C on the terminal is ours to handle
            )
        finally:
            os.close(fd)
        clock = current_clock()
        deadline = clock.monotonic() + START_TIMEOUT_S
        while True:
            if self._process.returncode is not None:
                raise LinkError(
                    f"Mosquitto exited at start (code {self._process.returncode})"
                    f"{self._errors_at_start() or self._log_tail()}"
                )
            try:
                async with asyncio.timeout(1.0):
                    _, writer = await asyncio.open_connection(self.host, self.port)
            except (OSError, TimeoutError):
                if clock.monotonic() > deadline:
                    await self._kill_process()
                    raise LinkError(
                        f"Mosquitto did not accept connections on {self.host}:{self.port} "
                        f"within {START_TIMEOUT_S:g} s{self._log_tail()}"
                    ) from None
                await clock.sleep(0.02)
                continue
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()
            return

    async def _keep_up(self) -> None:
        """Until stop() or kill(): a broker that exits is said, and started again (same
        port, configuration and persistence) up to ``restarts`` times in a row; the cells
        and the factory reconnect by themselves. One that will not start is said with what
        to do, and kept in ``failure``."""
        while (proc := self._process) is not None:
            code = await proc.wait()
            if self._meant_to_end or proc is not self._process:
                return
            how = f"killed by signal {-code}" if code < 0 else f"exit code {code}"
            self.say(
                f"Mosquitto on {self.host}:{self.port} stopped ({how}): starting it again "
                "on the same port with the same configuration and persisted sessions"
            )
            for attempt in range(1, self.restarts + 1):
                if attempt > 1:
                    await current_clock().sleep(RESTART_PAUSE_S * (attempt - 1))
                if self._meant_to_end:
                    return
                self._restarting = True
                try:
                    await self._launch()
                except (CellctlError, OSError) as e:
                    self.failure = e if isinstance(e, CellctlError) else LinkError(str(e))
                    self.say(f"Mosquitto did not start (attempt {attempt} of {self.restarts}): {e}")
                    continue
                finally:
                    self._restarting = False
                if self._meant_to_end:
                    return  # stopped while it started: stop() ends the new process
                self.failure = None
                self.say(
                    f"Mosquitto is back on {self.host}:{self.port}: the cells and the factory "
                    "reconnect by themselves"
                )
                break
            else:
                self.failure = LinkError(
                    f"Mosquitto on {self.host}:{self.port} stopped and did not start again in "
                    f"{self.restarts} attempts ({self.failure}): the cells and the factory "
                    f"cannot reach it; see its files in {self.directory}, then stop this "
                    "(Ctrl-C) and start it again"
                )
                self.say(str(self.failure))
                return

    def _errors_at_start(self) -> str:
        """The errors on the broker's stderr (its warning about root left out), or ""."""
        try:
            lines = self.stderr_path.read_text(encoding="utf-8", errors="replace").splitlines()
        except OSError:
            return ""
        errors = [line for line in lines if "Error" in line] or lines
        return ": " + " | ".join(errors[-3:]) if errors else ""

    def _log_tail(self) -> str:
        try:
            lines = self.log_path.read_text(encoding="utf-8", errors="replace").splitlines()
        except OSError:
            return ""
        return ": " + " | ".join(lines[-3:]) if lines else ""

    async def stop(self) -> None:
        """SIGTERM the broker (it saves its persistence file) and wait for it to exit."""
        await self._end_watch()
        proc = self._process
        if proc is None or proc.returncode is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGTERM)
        try:
            async with asyncio.timeout(STOP_TIMEOUT_S):
                await proc.wait()
        except TimeoutError:
            await self.kill()

    async def kill(self) -> None:
        """SIGKILL the broker (tests: a broker that dies without saving; not started again)."""
        await self._end_watch()
        await self._kill_process()

    async def _kill_process(self) -> None:
        proc = self._process
        if proc is None or proc.returncode is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        await proc.wait()

    async def _end_watch(self) -> None:
        """The broker is ended on purpose: the watch (if any) ends, and answers nothing."""
        self._meant_to_end = True
        watch, self._watch = self._watch, None
        if watch is None or watch is asyncio.current_task():
            return
        if not self._restarting:
            watch.cancel()
        # A start under way is let finish (cancelled, the process it spawns would be lost):
        # the watch then sees the stop and returns, and the caller ends the new process.
        with contextlib.suppress(asyncio.CancelledError):
            await watch

    async def restart(self) -> None:
        """Stop and start again on the same port; persisted sessions and messages survive."""
        await self.stop()
        await self.start()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()
