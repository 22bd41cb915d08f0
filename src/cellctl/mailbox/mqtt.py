"""The cell's mailbox on an MQTT broker: orders in, reports, state and status out.

``cellctl run`` starts it when cell.toml has ``[mailbox] url = "mqtt://HOST:PORT/PREFIX"``
(and ``credentials``); the SQLite mailbox stays the cell's record of every order and report::

    bridge = MqttBridge(settings, controller, mailbox, journal)
    task = asyncio.create_task(bridge.run())        # until bridge.stop()

Topics and payloads are in docs/factory.md. In short: an order arriving on ``PREFIX/orders``
is committed to the SQLite mailbox before anything else (an id seen before changes nothing
and has its accepted or rejected report published again, so the factory's re-sends are
answered); reports go out on ``PREFIX/reports`` in their mailbox order, each after the
broker's PUBACK, the last one sent kept in ``<cell>/state/mqtt.json`` (0600) so a restarted
cell sends what it had not; ``PREFIX/state`` (retained) on change; ``PREFIX/status`` is
``online``, and ``offline`` through the retained last will or a clean stop. A broker that goes
away is tried again with backoff; the cell keeps working meanwhile.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import ssl
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import urlsplit

import aiomqtt

from cellctl.cell.estimate import finish_estimate, measured, part_bounds
from cellctl.cell.journal import Journal
from cellctl.errors import UsageError
from cellctl.mailbox.base import INT64, Mailbox, Report

#: The payloads' format version (docs/factory.md).
VERSION = 1
#: Report kinds that answer an order: published again when its id comes again.
ANSWERS = ("order-accepted", "order-rejected")
#: Seconds between attempts to reach a broker that went away: from the first to the last.
BACKOFF_S = (0.2, 5.0)


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
        """From ``mqtt[s]://HOST:PORT/PREFIX`` and a credentials file (TOML, 0600)."""
        parts = urlsplit(url)
        if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname:
            raise UsageError(f"{url}: expected mqtt://HOST:PORT/PREFIX or mqtts://...")
        username, password = read_credentials(credentials)
        tls = parts.scheme == "mqtts"
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
        """An aiomqtt client with these settings and a persistent session."""
        context = None
        if self.tls:
            context = ssl.create_default_context(cafile=str(self.ca) if self.ca else None)
        return aiomqtt.Client(
            self.host,
            self.port,
            username=self.username,
            password=self.password,
            identifier=identifier,
            clean_session=False,
            will=will,
            tls_context=context,
            # A QoS 1 publish caught by a dropped connection fails only at this deadline.
            timeout=2.0,
        )


def read_credentials(path: Path) -> tuple[str, str]:
    """``username`` and ``password`` from a TOML file that only its owner may read."""
    try:
        mode = path.stat().st_mode
        data = tomllib.loads(path.read_text(encoding="utf-8"))
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


def report_payload(cell: str, r: Report) -> dict[str, Any]:
    return {
        "v": VERSION,
        "cell": cell,
        "seq": r.seq,
        "kind": r.kind,
        "order_id": r.order_id,
        "part_id": r.part_id,
        "text": r.text,
        "time": r.time,
        "data": r.data,
    }


def finite_number(value: object) -> bool:
    """A JSON number that is finite (not a bool, NaN, an infinity, or beyond any float)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer beyond any float
        return False


def parse_order(payload: bytes) -> dict[str, Any]:
    """An order message's fields, checked; UsageError says what is wrong."""
    try:
        data = json.loads(payload)
    except (ValueError, RecursionError) as e:
        raise UsageError(f"order is not JSON: {e}") from e
    if not isinstance(data, dict) or data.get("v") != VERSION:
        raise UsageError(f"order is not a version {VERSION} object")
    fields = {"id": str, "part_type": str, "qty": int, "priority": int}
    for key, kind in fields.items():
        value = data.get(key, 0 if key == "priority" else None)
        if not isinstance(value, kind) or isinstance(value, bool):
            raise UsageError(f"order field {key!r} must be {kind.__name__}, not {value!r}")
        if isinstance(value, int) and value not in INT64:
            raise UsageError(f"order field {key!r} must fit in 64 bits, not {value}")
    expires = data.get("expires")
    if expires is not None and not finite_number(expires):
        raise UsageError(f"order field 'expires' must be a time, not {expires!r}")
    return {**{k: data.get(k, 0) for k in fields}, "expires": expires}


class _Cell(Protocol):
    """What the bridge reads of the running controller."""

    config: Any
    machines: dict[str, Any]
    paused: bool
    listeners: list[Callable[[], None]]

    def poke(self) -> None: ...


class MqttBridge:
    """The cell's side of the factory's broker (see module docstring)."""

    def __init__(
        self,
        settings: MqttSettings,
        cell: _Cell,
        mailbox: Mailbox,
        journal: Journal,
        *,
        log: Callable[[str], None] = lambda text: None,
    ) -> None:
        self.settings = settings
        self.cell = cell
        self.mailbox = mailbox
        self.journal = journal
        self.log = log
        self.name: str = cell.config.name
        self.topic = {t: f"{settings.prefix}/{t}" for t in ("orders", "reports", "state", "status")}
        self._mark = cell.config.directory / "state" / "mqtt.json"
        #: Orders taken with an ``expires`` whose answer the broker has not yet acknowledged.
        self.expiring: dict[str, float] = {}
        self.sent_seq = self._load_mark()
        self.connected = asyncio.Event()
        self._changed = asyncio.Event()
        self._stopping = asyncio.Event()
        self._state_sent: dict[str, Any] | None = None
        self._state_at = 0.0
        self._resend: list[Report] = []

    # -- the last report sent ------------------------------------------------------------------

    def _load_mark(self) -> int:
        with contextlib.suppress(OSError, ValueError, TypeError, AttributeError):
            mark = json.loads(self._mark.read_text())
            self.expiring = {str(k): float(v) for k, v in mark.get("expiring", {}).items()}
            return int(mark["seq"])
        return 0

    def _save_mark(self) -> None:
        self._mark.parent.mkdir(parents=True, exist_ok=True)
        tmp = self._mark.with_suffix(".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            json.dump({"seq": self.sent_seq, "expiring": self.expiring}, f)
        os.replace(tmp, self._mark)

    def drop_expired(self) -> None:
        """Cancel each order taken before its ``expires`` whose acceptance the factory has not
        heard by then, if none of its parts has started: the factory may have given it to
        another cell. ``cellctl run`` calls it before the controller starts."""
        now = time.time()
        for oid, expires in list(self.expiring.items()):
            if now <= expires:
                continue
            unsent = [
                r
                for r in self.mailbox.reports(since_seq=self.sent_seq)
                if r.order_id == oid and r.kind in ANSWERS
            ]
            if not unsent or unsent[0].kind != "order-accepted":
                continue  # not taken, or refused: its answer goes out as it is
            try:
                self.journal.cancel_parts(oid)
                self.mailbox.set_order_state(oid, "cancelled", "expired before it was reported")
            except UsageError:
                continue  # a part has started: the order stays here and is reported
            self.mailbox.post_report(
                "order-rejected",
                f"order {oid}: expired before the factory heard it was accepted; cancelled here",
                order_id=oid,
                data={"expired": True},
            )
            self.log(f"mailbox: order {oid} cancelled: its acceptance was not reported in time")

    # -- running -------------------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, serve, and reconnect with backoff until :meth:`stop`."""
        self.cell.listeners.append(self._changed.set)
        delay = BACKOFF_S[0]
        told = False
        try:
            while not self._stopping.is_set():
                try:
                    await self._session()
                    delay = BACKOFF_S[0]
                except (aiomqtt.MqttError, OSError, ValueError) as e:
                    # ValueError, OSError: a message or a file the session could not handle
                    # (a mark that cannot be written, say). Never end silently: the cell
                    # would go on without a mailbox and the factory would think it online.
                    self.connected.clear()
                    if not told:
                        self.log(f"mailbox: {self.settings.url}: {e} (trying again)")
                        told = True
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(delay):
                            await self._stopping.wait()
                    delay = min(delay * 2, BACKOFF_S[1])
                else:
                    told = False
        finally:
            with contextlib.suppress(ValueError):
                self.cell.listeners.remove(self._changed.set)

    async def stop(self) -> None:
        """Publish ``offline`` and disconnect (the session's orders wait at the broker)."""
        self._stopping.set()

    async def _session(self) -> None:
        will = aiomqtt.Will(self.topic["status"], "offline", qos=1, retain=True)
        # The session is the prefix's: one cell a prefix, whatever the cell is called.
        ident = "cellctl-cell-" + self.settings.prefix.replace("/", "-")
        async with self.settings.client(ident, will) as client:
            await client.subscribe(self.topic["orders"], qos=1)
            await client.publish(self.topic["status"], "online", qos=1, retain=True)
            self.connected.set()
            self.log(f"mailbox: {self.settings.url}")
            receiver = asyncio.create_task(self._receive(client))
            try:
                while not self._stopping.is_set():
                    await self._publish_reports(client)
                    await self._publish_state(client)
                    if receiver.done():
                        receiver.result()  # the connection broke: raises its MqttError
                    self._changed.clear()
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(self.cell.config.poll_period):
                            await self._changed.wait()
                await self._publish_reports(client)
                await client.publish(self.topic["status"], "offline", qos=1, retain=True)
            finally:
                receiver.cancel()
                with contextlib.suppress(BaseException):
                    await receiver
                self.connected.clear()

    # -- orders in -----------------------------------------------------------------------------

    async def _receive(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            self.take_order(bytes(message.payload) if message.payload is not None else b"")
            self._changed.set()

    def take_order(self, payload: bytes) -> None:
        """Commit an order message to the mailbox; answer a repeated id again."""
        try:
            fields = parse_order(payload)
        except UsageError as e:
            self.log(f"mailbox: order refused: {e}")
            return
        oid = fields["id"]
        expires = fields["expires"]
        if expires is not None and time.time() > expires and not self._known(oid):
            # Sent to this cell, then not taken in time: the factory has given it to another.
            self.mailbox.post_report(
                "order-rejected", f"order {oid}: expired", order_id=oid, data={"expired": True}
            )
            return
        if expires is not None and not self._known(oid):
            self.expiring[oid] = float(expires)  # written before the order is committed
            self._save_mark()
        try:
            order, new = self.mailbox.post_order(
                fields["part_type"], fields["qty"], fields["priority"], fields["id"]
            )
        except UsageError as e:
            self.mailbox.post_report("order-rejected", f"order {oid}: {e}", order_id=oid)
            return
        if new:
            self.cell.poke()
            return
        answers = [r for r in self.mailbox.reports() if r.order_id == order.id]
        answers = [r for r in answers if r.kind in ANSWERS]
        if answers and answers[-1].seq <= self.sent_seq:
            self._resend.append(answers[-1])  # sent before: the factory asks again

    def _cancelled(self, order_id: str | None) -> bool:
        if order_id is None or order_id not in self.expiring:
            return False
        with contextlib.suppress(UsageError):
            return self.mailbox.get_order(order_id).state == "cancelled"
        return False

    def _known(self, order_id: str) -> bool:
        with contextlib.suppress(UsageError):
            self.mailbox.get_order(order_id)
            return True
        return False

    # -- reports, state out ----------------------------------------------------------------------

    async def _publish_reports(self, client: aiomqtt.Client) -> None:
        resend, self._resend = self._resend, []
        for r in resend:
            await self._publish_report(client, r)
        self.drop_expired()
        for r in self.mailbox.reports(since_seq=self.sent_seq):
            cancelled = r.kind == "order-accepted" and self._cancelled(r.order_id)
            if not cancelled:  # an acceptance taken back by drop_expired is never told
                await self._publish_report(client, r)
            self.sent_seq = r.seq
            if r.kind in ANSWERS and not cancelled and r.order_id is not None:
                self.expiring.pop(r.order_id, None)  # the factory knows now
            self._save_mark()

    async def _publish_report(self, client: aiomqtt.Client, r: Report) -> None:
        payload = json.dumps(report_payload(self.name, r))
        await client.publish(self.topic["reports"], payload, qos=1)  # returns after PUBACK

    def state(self) -> dict[str, Any]:
        """The retained state message (without its time)."""
        types = self.cell.config.parts
        open_parts = self.journal.parts(statuses=["waiting", "active", "held"])
        durations = measured(self.journal)
        bounds = part_bounds(types, durations)
        orders = [
            o for o in self.mailbox.orders() if o.state not in ("done", "failed", "cancelled")
        ]
        return {
            "v": VERSION,
            "cell": self.name,
            "paused": self.cell.paused,
            "part_types": {name: {"bound_s": round(b, 3)} for name, b in bounds.items()},
            "machines": {
                name: {"kind": m.kind, "state": m.state, "in_service": m.in_service}
                for name, m in self.cell.machines.items()
            },
            "orders_open": len(orders),
            "parts_open": len(open_parts),
            "finish_estimate_s": round(
                finish_estimate(types, [p.part_type for p in open_parts], durations), 3
            ),
        }

    async def _publish_state(self, client: aiomqtt.Client) -> None:
        """The retained state, when it changed, at most once a poll period."""
        if time.monotonic() - self._state_at < self.cell.config.poll_period:
            return
        state = self.state()
        if state == self._state_sent:
            return
        payload = json.dumps({**state, "time": time.time()})
        await client.publish(self.topic["state"], payload, qos=1, retain=True)
        self._state_sent = state
        self._state_at = time.monotonic()
