"""Reaching the broker: where it is and how to log in, what went wrong, and trying again.

Both ends of the factory's broker (a cell's :class:`~cellctl.mailbox.mqtt.MqttBridge` and the
:class:`~cellctl.factory.controller.FactoryController`) connect through this module::

    settings = MqttSettings.load("mqtts://broker:8883/cellctl/cell1", creds, ca=Path("ca.crt"))
    reconnect = Reconnect(settings, stop, log=print, what="mailbox")
    await reconnect.run(session)     # session() connects with settings.client(...), calls
                                     # reconnect.connected() once in, returns when done

A broker that goes away is tried again with backoff (:data:`BACKOFF_S`); the log says once
what is wrong, in words: a wrong password, a certificate not signed by the CA given
(:class:`TlsRefused`), or ``mqtt://`` to a TLS port and the other way round
(:class:`WrongScheme`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
import tomllib
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self
from urllib.parse import urlsplit

import aiomqtt

from cellctl.clock import current_clock
from cellctl.errors import CellctlError, LinkClosed, LinkError, LinkTimeout, UsageError
from cellctl.files import read_text

#: Seconds between attempts to reach a broker that went away: from the first to the last.
BACKOFF_S = (0.2, 5.0)
#: A session that was in and broke within this many seconds was cut short.
SHORT_SESSION_S = 5.0
#: Sessions cut short in a row before the log says another client may hold the same user:
#: the broker keeps one connection per user (its client id), and drops the older one each
#: time the other connects again, so two of them take turns without end.
CUT_SHORT_TOLD = 3
#: How long the look at a port that would not speak MQTT may take (is it TLS or not?).
PROBE_S = 2.0
#: How long the library waits for the broker's answer (CONNACK, a publish's PUBACK).
ANSWER_S = 2.0


class TlsRefused(LinkError):
    """The broker's certificate is not one the client may trust (another CA, another name)."""


class WrongScheme(LinkError):
    """``mqtt://`` to a port that speaks TLS, or ``mqtts://`` to one that does not."""


@dataclass(frozen=True)
class MqttSettings:
    """Where the broker is, the topics' prefix and how to log in."""

    host: str
    port: int
    prefix: str
    username: str
    password: str
    tls: bool = False
    ca: Path | None = None

    @classmethod
    def load(cls, url: str, credentials: Path, ca: Path | None = None) -> MqttSettings:
        """From ``mqtt[s]://HOST:PORT/PREFIX`` and a credentials file (TOML, 0600); ``ca`` is
        the CA certificate (PEM) an ``mqtts://`` broker's certificate must be signed by
        (default: the system's CAs)."""
        parts = urlsplit(url)
        if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname:
            raise UsageError(f"{url}: expected mqtt://HOST:PORT/PREFIX or mqtts://...")
        tls = parts.scheme == "mqtts"
        if ca is not None and not tls:
            raise UsageError(f"{url}: a CA is given ({ca}): use mqtts:// to speak TLS")
        if ca is not None and not ca.is_file():
            raise UsageError(f"{ca}: no such CA certificate file")
        username, password = read_credentials(credentials)
        return cls(
            host=parts.hostname,
            port=parts.port or (8883 if tls else 1883),
            prefix=parts.path.strip("/"),
            username=username,
            password=password,
            tls=tls,
            ca=ca,
        )

    @property
    def url(self) -> str:
        scheme = "mqtts" if self.tls else "mqtt"
        return f"{scheme}://{self.host}:{self.port}/{self.prefix}"

    def client(self, identifier: str, will: aiomqtt.Will | None = None) -> aiomqtt.Client:
        """An aiomqtt client with these settings and a persistent session.

        A broker that binds client ids to users (docs/factory.md) replaces ``identifier``
        with the user name: the session is the user's."""
        context = None
        if self.tls:
            try:
                context = ssl.create_default_context(cafile=str(self.ca) if self.ca else None)
            except (ssl.SSLError, OSError) as e:
                raise UsageError(f"{self.ca}: not a CA certificate (PEM): {e}") from None
        return _Client(
            self.host,
            self.port,
            username=self.username,
            password=self.password,
            identifier=identifier,
            clean_session=False,
            will=will,
            tls_context=context,
            # A QoS 1 publish caught by a dropped connection fails only at this deadline.
            timeout=ANSWER_S,
        )

    def unanswered(self, error: BaseException) -> LinkError | None:
        """The library's words for a broker that stopped answering or went away, in cellctl's:
        "Operation timed out" (the broker did not answer in time), "[code:4] The client is
        not currently connected.", "[code:7] The connection was lost.", "[code:128]
        Unspecified error" (the connection dropped); None for anything else."""
        where = f"{self.host}:{self.port}"
        if not isinstance(error, aiomqtt.MqttError):
            return None
        if "timed out" in str(error):
            return LinkTimeout(f"the broker at {where} did not answer within {ANSWER_S:g} s")
        code = getattr(error, "rc", None)
        if isinstance(error, aiomqtt.MqttCodeError) and getattr(code, "value", code) in LOST:
            return LinkClosed(f"the connection to the broker at {where} was lost")
        return None

    async def explain(self, error: BaseException) -> CellctlError | BaseException:
        """``error`` from a connection attempt, in words when the cause is TLS: a certificate
        the CA does not vouch for, or a scheme the port does not speak (it looks once)."""
        where = f"{self.host}:{self.port}"
        cause = error.__context__ or error.__cause__
        if isinstance(cause, ssl.SSLCertVerificationError):
            trusted = f"the CA in {self.ca}" if self.ca else "a CA this system trusts"
            if cause.verify_code == 62:  # X509_V_ERR_HOSTNAME_MISMATCH
                return TlsRefused(
                    f"TLS: the broker's certificate at {where} is not for {self.host}"
                )
            return TlsRefused(
                f"TLS: the broker's certificate at {where} is not signed by {trusted}"
                f" ({cause.verify_message})"
            )
        if isinstance(cause, ConnectionRefusedError):
            return LinkError(f"nothing listens at {where}: is the broker running there?")
        if "authori" in str(error).lower():
            return error  # a wrong user name or password: said as the broker says it
        if not self.tls and await _speaks_tls(self.host, self.port):
            return WrongScheme(f"the broker at {where} speaks TLS: use mqtts://{where}/...")
        if self.tls and await _speaks_plain_mqtt(self.host, self.port):
            return WrongScheme(f"the broker at {where} does not speak TLS: use mqtt://{where}/...")
        return self.unanswered(error) or error


#: The library's codes for a connection that went away: paho's "not currently connected" (4)
#: and "connection lost" (7), and MQTT's "unspecified error" (128, what an unexpected
#: disconnection is given).
LOST = (4, 7, 128)


class _Client(aiomqtt.Client):
    """aiomqtt's client, whose futures of the connection's end are always looked at.

    The library sets an exception on the future of an unexpected disconnection (a broker
    that stopped answering) even when nobody waits for it any more (the session ended on a
    publish's deadline first): asyncio then prints "Future exception was never retrieved"
    and a traceback into the log. The session's own error says it, in words, once
    (:class:`Reconnect`)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._look_after()

    def _look_after(self) -> None:
        for future in (self._connected, self._disconnected):
            future.add_done_callback(_retrieve)

    async def __aenter__(self) -> Self:
        try:
            return await super().__aenter__()
        finally:
            self._look_after()  # the futures made anew for this connection

    async def __aexit__(self, *exc: Any) -> None:
        try:
            await super().__aexit__(*exc)
        finally:
            self._look_after()


def _retrieve(future: asyncio.Future[None]) -> None:
    """Look at ``future``'s exception, so that asyncio does not print it as never retrieved."""
    if not future.cancelled():
        future.exception()


#: An MQTT 3.1.1 CONNECT without a user or client id: any broker answers it with a CONNACK
#: (refusing it), which tells a plain MQTT port.
_CONNECT = bytes.fromhex("100c00044d5154540402003c0000")
_CONNACK = 0x20


async def _speaks_tls(host: str, port: int) -> bool:
    """Whether ``host:port`` completes a TLS handshake (certificates unchecked: it only asks
    whether the port speaks TLS at all)."""
    context = ssl.create_default_context()
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    try:
        async with asyncio.timeout(PROBE_S):
            _, writer = await asyncio.open_connection(host, port, ssl=context)
    except (OSError, TimeoutError):  # ssl.SSLError is an OSError
        return False
    writer.close()
    with contextlib.suppress(OSError):
        await writer.wait_closed()
    return True


async def _speaks_plain_mqtt(host: str, port: int) -> bool:
    """Whether ``host:port`` answers a plain MQTT CONNECT with a CONNACK."""
    try:
        async with asyncio.timeout(PROBE_S):
            reader, writer = await asyncio.open_connection(host, port)
            try:
                writer.write(_CONNECT)
                await writer.drain()
                first = await reader.read(1)
            finally:
                writer.close()
                with contextlib.suppress(OSError):
                    await writer.wait_closed()
    except (OSError, TimeoutError):
        return False
    return first == bytes([_CONNACK])


def read_credentials(path: Path) -> tuple[str, str]:
    """``username`` and ``password`` from a TOML file that only its owner may read."""
    try:
        mode = path.stat().st_mode
        data = tomllib.loads(read_text(path))
    except OSError as e:
        raise UsageError(f"{path}: cannot read the credentials: {e.strerror}") from e
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise UsageError(f"{path}: not a credentials file (TOML): {e}") from e
    if mode & 0o077:
        raise UsageError(f"{path}: others may read it: chmod 600 {path}")
    user, password = data.get("username"), data.get("password")
    if not isinstance(user, str) or not isinstance(password, str):
        raise UsageError(f'{path}: needs username = "..." and password = "..."')
    return user, password


#: The MQTT library's logger (aiomqtt's, which paho writes to when a read or write fails).
MQTT_LIBRARY_LOGGER = "mqtt"


def quiet_mqtt_library() -> None:
    """Keep the MQTT library's own log lines ("failed to receive on socket: [Errno 32] Broken
    pipe") out of the run log: raw, without a time, they repeat what :class:`Reconnect` says
    in cellctl's words (as pymodbus is quieted for the PLC)."""
    logging.getLogger(MQTT_LIBRARY_LOGGER).setLevel(logging.CRITICAL)


class Reconnect:
    """Run a session on the broker until it returns or ``stop`` is set; a session that ends on
    an error is started again after a backoff (0.2 s doubling up to 5 s, back to 0.2 s once
    a session is in). Each new problem is logged once: ``WHAT: URL: problem (trying again)``;
    the library's own lines are quieted (:func:`quiet_mqtt_library`): every link to the
    broker (a cell's mailbox, the system controller) keeps one set of words.
    """

    def __init__(
        self,
        settings: MqttSettings,
        stop: asyncio.Event,
        *,
        log: Callable[[str], None],
        what: str,
        errors: tuple[type[BaseException], ...] = (aiomqtt.MqttError, OSError, ValueError),
        twin: str = "another program connected as the same user",
    ) -> None:
        quiet_mqtt_library()
        self.settings = settings
        self.stop = stop
        self.log = log
        self.what = what
        self.errors = errors
        self.twin = twin
        #: The last problem, typed (TlsRefused, WrongScheme, ...); None once connected.
        self.problem: BaseException | None = None
        self._delay = BACKOFF_S[0]
        self._told: str | None = None
        self._in = False
        self._in_at = 0.0
        self._cut_short = 0  # sessions in a row that broke within SHORT_SESSION_S

    def connected(self) -> None:
        """The session is in: the next problem is told, and tried again soon."""
        self._delay = BACKOFF_S[0]
        self._told = None
        self.problem = None
        self._in = True
        self._in_at = current_clock().monotonic()

    async def run(
        self, session: Callable[[], Awaitable[None]], on_drop: Callable[[], None] = lambda: None
    ) -> None:
        while not self.stop.is_set():
            self._in = False
            try:
                await session()
                return
            except self.errors as e:
                on_drop()
                # A connection that was in and broke needs no look at TLS.
                self.problem = (
                    (self.settings.unanswered(e) or e)
                    if self._in
                    else await self.settings.explain(e)
                )
                if self._in:
                    lasted = current_clock().monotonic() - self._in_at
                    self._cut_short = self._cut_short + 1 if lasted < SHORT_SESSION_S else 0
                else:
                    self._cut_short = 0  # not let in at all: another problem, told as it is
                if self._cut_short >= CUT_SHORT_TOLD:
                    self.problem = CellctlError(
                        f"the broker drops this connection again and again within "
                        f"{SHORT_SESSION_S:g} s of making it: is {self.twin} "
                        f"({self.settings.username})? The broker keeps one connection per "
                        "user: the two take turns"
                    )
                text = f"{self.what}: {self.settings.url}: {self.problem} (trying again)"
                if text != self._told:
                    self.log(text)
                    self._told = text
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(self._delay):
                        await self.stop.wait()
                self._delay = min(self._delay * 2, BACKOFF_S[1])
