"""The cell's mailbox on an MQTT broker: orders in, reports, state and status out.

``cellctl run`` starts it when cell.toml has ``[mailbox] url = "mqtt://HOST:PORT/PREFIX"``
(and ``credentials``); the SQLite mailbox stays the cell's record of every order and report::

    bridge = MqttBridge(settings, controller, mailbox, journal)
    task = asyncio.create_task(bridge.run())        # until bridge.stop()

Topics and payloads are in docs/factory.md, their models in :mod:`cellctl.mailbox.wire`. In
short: an order arriving on ``PREFIX/orders`` is committed to the SQLite mailbox before
anything else (an id seen before changes nothing and has its accepted or rejected report
published again, so the factory's re-sends are answered); reports go out on
``PREFIX/reports`` in their mailbox order with the mailbox's epoch, each after the broker's
PUBACK, the last one sent kept with that epoch in ``<cell>/state/mqtt.json`` (0600) so a
restarted cell sends what it had not; the factory's ask on ``PREFIX/orders`` has the reports
after a seq sent again; ``PREFIX/state`` (retained) on change; ``PREFIX/status`` is
``online``, and ``offline`` through the retained last will or a clean stop. A message that
fails its model is logged and dropped. A broker that goes away is tried again with backoff
(:class:`~cellctl.mailbox.mqttlink.Reconnect`); the cell keeps working meanwhile.

Given a ``cancel`` (``cellctl run`` hands it the control API's ``orders.cancel``:
:func:`cellctl.factory.cancel.cell_canceller`), the factory's cancel of an order on
``PREFIX/orders`` is the cell's own operator's cancel, made as ``factory:WHO``: it reports
``order-cancelled``, or ``cancel-refused`` with the cell's words when that cancel refuses
(a part of the order has started)::

    bridge = MqttBridge(settings, controller, mailbox, journal, cancel=cell_canceller(api))

Given a ``planner`` (``[mailbox] plan_period``: :func:`cellctl.service.planning.own_plan`), the
bridge also plays its cell's open work forward, one plan at a time, every ``plan_period``
seconds and when its open orders or its machines' service change, and publishes when the
plan finishes (``plan_finish_s``, ``planned_at``) in the retained state::

    bridge = MqttBridge(settings, controller, mailbox, journal, planner=plan, plan_period=300)
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Protocol

import aiomqtt

from cellctl.cell.config import PartType
from cellctl.cell.estimate import finish_estimate, measured, part_bounds
from cellctl.cell.journal import Journal
from cellctl.cell.shift import cell_time_scale
from cellctl.clock import Clock, current_clock
from cellctl.errors import CellctlError, UsageError
from cellctl.mailbox.base import FINAL_STATES, Mailbox, Report
from cellctl.mailbox.mqttlink import BACKOFF_S, MqttSettings, Reconnect, read_credentials
from cellctl.mailbox.wire import (
    AskMessage,
    CancelMessage,
    MachineState,
    OrderMessage,
    PartTypeState,
    ReportKind,
    StateMessage,
    WireError,
    parse_to_cell,
    report_message,
)

__all__ = [
    "ANSWERS",
    "BACKOFF_S",
    "Canceller",
    "MqttBridge",
    "MqttSettings",
    "PlanEstimate",
    "Planner",
    "read_credentials",
]

#: Report kinds that answer an order: published again when its id comes again.
ANSWERS = (ReportKind.ORDER_ACCEPTED, ReportKind.ORDER_REJECTED)
#: Order states still to be worked on (a change among them is a reason to plan again).
OPEN_ORDER_STATES = ("posted", "accepted", "in-progress", "held")
#: Seconds at least between the end of one plan of the cell's work and the start of the next
#: (a burst of order changes is one plan more, not one each).
PLAN_GAP_S = 1.0


@dataclass(frozen=True)
class PlanEstimate:
    """When the cell's plan of its open work finishes: ``finish_s`` seconds after
    ``planned_at`` (unix seconds, when its state was taken)."""

    planned_at: float
    finish_s: float


#: Plays the cell's open work forward (off the event loop) and says when it finishes.
Planner = Callable[[], Awaitable[PlanEstimate]]
#: Cancels an order as the cell's operator would, for ``(order id, who)``: the cell's words,
#: or a :class:`CellctlError` (a UsageError) with them when the cell's cancel refuses.
Canceller = Callable[[str, str], Awaitable[str]]


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
        clock: Clock | None = None,
        planner: Planner | None = None,
        plan_period: float = 300.0,
        cancel: Canceller | None = None,
    ) -> None:
        self._clock = clock
        self._cancel = cancel
        #: The factory's cancels taken off the topic, to act on in order (an await each).
        self._cancels: list[CancelMessage] = []
        #: Per order, the last cancel request answered (a request sent again is not).
        self._answered: dict[str, float] = {}
        self._planner = planner
        self.plan_period = plan_period
        #: The last plan of the cell's open work (None: none yet, or no planner).
        self.plan: PlanEstimate | None = None
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
        #: The factory asked for the reports after this seq again (None: it did not).
        self._replay_after: int | None = None

    # -- the last report sent ------------------------------------------------------------------

    @property
    def clock(self) -> Clock:
        """What the bridge reads the time from: the clock given, else the running loop's."""
        return self._clock or current_clock()

    def _load_mark(self) -> int:
        with contextlib.suppress(OSError, ValueError, TypeError, AttributeError, KeyError):
            mark = json.loads(self._mark.read_text())
            if mark["epoch"] != self.mailbox.epoch:
                return 0  # a mark of a mailbox that is gone: this one's reports are all unsent
            self.expiring = {str(k): float(v) for k, v in mark.get("expiring", {}).items()}
            return int(mark["seq"])
        return 0

    def _save_mark(self) -> None:
        self._mark.parent.mkdir(parents=True, exist_ok=True)
        tmp = self._mark.with_suffix(".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            mark = {"epoch": self.mailbox.epoch, "seq": self.sent_seq, "expiring": self.expiring}
            json.dump(mark, f)
        os.replace(tmp, self._mark)

    def drop_expired(self) -> None:
        """Cancel each order taken before its ``expires`` whose acceptance the factory has not
        heard by then, if none of its parts has started: the factory may have given it to
        another cell. ``cellctl run`` calls it before the controller starts."""
        now = self.clock.now()
        for oid, expires in list(self.expiring.items()):
            if now <= expires:
                continue
            unsent = [
                r
                for r in self.mailbox.reports(since_seq=self.sent_seq)
                if r.order_id == oid and r.kind in ANSWERS
            ]
            if not unsent or unsent[0].kind != ReportKind.ORDER_ACCEPTED:
                continue  # not taken, or refused: its answer goes out as it is
            try:
                self.journal.cancel_parts(oid)
                self.mailbox.set_order_state(oid, "cancelled", "expired before it was reported")
            except UsageError:
                continue  # a part has started: the order stays here and is reported
            self.mailbox.post_report(
                ReportKind.ORDER_REJECTED,
                f"order {oid}: expired before the factory heard it was accepted; cancelled here",
                order_id=oid,
                data={"expired": True},
            )
            self.log(f"mailbox: order {oid} cancelled: its acceptance was not reported in time")

    # -- running -------------------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, serve, and reconnect with backoff until :meth:`stop`."""
        self.cell.listeners.append(self._changed.set)
        # ValueError, OSError too: a file the session could not handle (a mark that cannot
        # be written, say). Never end silently: the cell would go on without a mailbox and
        # the factory would think it online.
        self._reconnect = Reconnect(
            self.settings,
            self._stopping,
            log=self.log,
            what="mailbox",
            twin="another controller of this cell (`cellctl run`), on another host",
        )
        planning = None
        if self._planner is not None:
            planning = asyncio.create_task(self._plan_loop(self._planner), name="own-plan")
        try:
            await self._reconnect.run(self._session, on_drop=self.connected.clear)
        finally:
            with contextlib.suppress(ValueError):
                self.cell.listeners.remove(self._changed.set)
            if planning is not None:
                planning.cancel()
                with contextlib.suppress(BaseException):
                    await planning

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
            self._reconnect.connected()
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

    # -- the cell's own plan --------------------------------------------------------------------

    def _plan_key(self) -> tuple[Any, ...]:
        """What a plan is of: the open orders' ids and states, the machines out of service."""
        orders = self.mailbox.orders(states=list(OPEN_ORDER_STATES))
        out = sorted(name for name, m in self.cell.machines.items() if not m.in_service)
        return (tuple((o.id, o.state, o.qty) for o in orders), tuple(out))

    async def _plan_loop(self, planner: Planner) -> None:
        """Plan the cell's work, one plan at a time, every ``plan_period`` and on a change."""
        clock = self.clock
        key: tuple[Any, ...] | None = None
        last = float("-inf")
        while not self._stopping.is_set():
            now_key = self._plan_key()
            if now_key != key or clock.monotonic() - last >= self.plan_period:
                key = now_key
                try:
                    self.plan = await planner()
                except Exception as e:  # the factory counts this cell by its bound meanwhile
                    self.plan = None
                    self.log(f"mailbox: the plan of the cell's own work failed: {e}"[:300])
                last = clock.monotonic()
                self._changed.set()
                await clock.sleep(PLAN_GAP_S)
            else:
                await clock.sleep(self.cell.config.poll_period)

    # -- orders in -----------------------------------------------------------------------------

    async def _receive(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            payload = message.payload if isinstance(message.payload, bytes) else b""
            try:
                self.take_order(payload)
                await self.take_cancels()
            except Exception as e:  # nothing that arrives on a topic ends the cell's link
                self._cancels.clear()
                self.log(f"mailbox: {message.topic.value}: a message dropped: {e!r}"[:300])
            self._changed.set()

    def take_order(self, payload: bytes) -> None:
        """Commit an order message to the mailbox and answer a repeated id again; take the
        factory's ask for reports again; or keep the factory's cancel for
        :meth:`take_cancels`. A message that is none of them is logged and dropped."""
        try:
            message = parse_to_cell(payload)
        except WireError as e:
            self.log(f"mailbox: {self.topic['orders']}: order refused: {e.reason}")
            return
        if isinstance(message, AskMessage):
            self._asked(message)
        elif isinstance(message, CancelMessage):
            self._cancels.append(message)
        else:
            self._take(message)

    async def take_cancels(self) -> None:
        """Act on the factory's cancels taken by :meth:`take_order`, in the order they came."""
        while self._cancels:
            await self._cancel_order(self._cancels.pop(0))

    async def _cancel_order(self, ask: CancelMessage) -> None:
        oid = ask.id
        if self._answered.get(oid) == ask.asked:
            return  # the factory sent it again before it heard the answer
        try:
            state = self.mailbox.get_order(oid).state
        except UsageError:
            # Not here: the order never reached the cell (every order message the factory
            # sent before this cancel comes before it on the topic): none of it is made.
            self._answered[oid] = ask.asked
            self.mailbox.post_report(
                ReportKind.ORDER_CANCELLED,
                f"order {oid} cancelled by the factory before it reached this cell",
                order_id=oid,
            )
            return
        if state in FINAL_STATES:
            return  # its end is reported already: that answers the factory
        if self._cancel is None:
            self._refuse(ask, "this cell's controller takes no cancel from the factory")
            return
        try:
            said = await self._cancel(oid, ask.by)
        except CellctlError as e:  # the cell's own cancel refuses it, in its own words
            self._refuse(ask, str(e))
            return
        reason = f": {ask.reason}" if ask.reason else ""
        with contextlib.suppress(UsageError):  # who and why, on the cell's order too
            self.mailbox.set_order_state(
                oid, "cancelled", f"cancelled by the factory ({ask.by}){reason}"
            )
        # Cancelled by the factory, not taken back by drop_expired: its acceptance (if not
        # yet sent) goes out as it is, not withdrawn.
        if self.expiring.pop(oid, None) is not None:
            self._save_mark()
        self._answered[oid] = ask.asked
        self.log(f"mailbox: {said}: asked by {ask.by} at the factory{reason}")

    def _refuse(self, ask: CancelMessage, why: str) -> None:
        self._answered[ask.id] = ask.asked
        self.mailbox.post_report(
            ReportKind.CANCEL_REFUSED,
            why,  # the cell's own words: its kind says what was refused
            order_id=ask.id,
            data={"asked": ask.asked, "by": ask.by},
        )
        self.log(f"mailbox: the factory's cancel of order {ask.id} refused: {why}")

    def _asked(self, ask: AskMessage) -> None:
        if ask.epoch != self.mailbox.epoch:
            self.log(f"mailbox: the factory asks for reports of a mailbox gone ({ask.epoch})")
            return
        if ask.after < self.sent_seq:
            # Two asks before the next batch of reports: the earlier seq covers both.
            if self._replay_after is None or ask.after < self._replay_after:
                self._replay_after = ask.after
            self.log(f"mailbox: the factory asks again for the reports after {ask.after}")

    def _take(self, order: OrderMessage) -> None:
        oid = order.id
        expires = order.expires
        if expires is not None and self.clock.now() > expires and not self._known(oid):
            # Sent to this cell, then not taken in time: the factory has given it to another.
            # Sent again (a cell that was stopped finds each resend queued): the one answer.
            said = [
                r
                for r in self.mailbox.reports()
                if r.order_id == oid and r.kind == ReportKind.ORDER_REJECTED
            ]
            if said:
                if said[-1].seq <= self.sent_seq:
                    self._resend.append(said[-1])
                return
            self.mailbox.post_report(
                ReportKind.ORDER_REJECTED,
                f"order {oid}: expired",
                order_id=oid,
                data={"expired": True},
            )
            return
        if expires is not None and not self._known(oid):
            self.expiring[oid] = float(expires)  # written before the order is committed
            self._save_mark()
        try:
            taken, new = self.mailbox.post_order(
                order.part_type, order.qty, order.priority, oid, due=order.due
            )
        except UsageError as e:
            self.mailbox.post_report(ReportKind.ORDER_REJECTED, f"order {oid}: {e}", order_id=oid)
            return
        if new:
            self.cell.poke()
            return
        answers = [r for r in self.mailbox.reports() if r.order_id == taken.id]
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
        if self._replay_after is not None:
            # Published before: the marks stay as they are, each goes out as it went then.
            for r in self.mailbox.reports(since_seq=self._replay_after):
                if r.seq > self.sent_seq:
                    break
                await self._publish_report(client, r)
                self._replay_after = r.seq
            self._replay_after = None
        self.drop_expired()
        for r in self.mailbox.reports(since_seq=self.sent_seq):
            await self._publish_report(client, r)
            self.sent_seq = r.seq
            cancelled = self._withdrawn(r)
            if r.kind in ANSWERS and not cancelled and r.order_id is not None:
                self.expiring.pop(r.order_id, None)  # the factory knows now
            self._save_mark()

    def _withdrawn(self, r: Report) -> bool:
        """An acceptance taken back by :meth:`drop_expired`: sent marked so, it moves nothing."""
        return r.kind == ReportKind.ORDER_ACCEPTED and self._cancelled(r.order_id)

    async def _publish_report(self, client: aiomqtt.Client, r: Report) -> None:
        message = report_message(self.name, self.mailbox.epoch, r, withdrawn=self._withdrawn(r))
        # Returns after the broker's PUBACK.
        await client.publish(self.topic["reports"], message.model_dump_json(), qos=1)

    def state(self) -> dict[str, Any]:
        """The retained state message's fields (without its time)."""
        types = self.cell.config.parts
        open_parts = self.journal.parts(statuses=["waiting", "active", "held"])
        durations = measured(self.journal)
        # The cell's own seconds: what it measured, and its guesses at its time scale.
        scale = cell_time_scale(self.cell.config)
        bounds = part_bounds(types, durations, time_scale=scale)
        orders = [
            o for o in self.mailbox.orders() if o.state not in ("done", "failed", "cancelled")
        ]
        return {
            "cell": self.name,
            "paused": self.cell.paused,
            "part_types": {
                name: PartTypeState(bound_s=round(b, 3), machines=self._needs(types[name]))
                for name, b in bounds.items()
            },
            "machines": {
                name: MachineState(kind=m.kind, state=m.state, in_service=m.in_service)
                for name, m in self.cell.machines.items()
            },
            "orders_open": len(orders),
            "parts_open": len(open_parts),
            "finish_estimate_s": round(
                finish_estimate(
                    types, [p.part_type for p in open_parts], durations, time_scale=scale
                ),
                3,
            ),
            **self._plan_fields(),
        }

    def _needs(self, part_type: PartType) -> tuple[str, ...]:
        """The machines a part of ``part_type`` needs in service: the robot, the mills of its
        route, and the PLC (conveyor and doors) where the cell has one."""
        config = self.cell.config
        route = [config.robot.name, *(step.mill for step in part_type.route), "plc"]
        return tuple(name for name in dict.fromkeys(route) if name in self.cell.machines)

    def _plan_fields(self) -> dict[str, float]:
        """``plan_finish_s`` and ``planned_at`` of the last plan (none: no fields)."""
        if self.plan is None:
            return {}
        return {
            "plan_finish_s": round(self.plan.finish_s, 3),
            "planned_at": round(self.plan.planned_at, 3),
        }

    async def _publish_state(self, client: aiomqtt.Client) -> None:
        """The retained state, when it changed, at most once a poll period."""
        if self.clock.monotonic() - self._state_at < self.cell.config.poll_period:
            return
        state = self.state()
        if state == self._state_sent:
            return
        # A cell that does not plan sends no plan fields (as before they were).
        message = StateMessage(**state, time=self.clock.now())
        payload = message.model_dump_json(exclude_none=True)
        await client.publish(self.topic["state"], payload, qos=1, retain=True)
        self._state_sent = state
        self._state_at = self.clock.monotonic()
