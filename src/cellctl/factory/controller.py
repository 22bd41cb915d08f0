"""The system controller: orders from the factory's store to the cells over MQTT, and back.

::

    with FactoryStore(config.state_path) as store:
        factory = FactoryController(config, store, log=print)
        await factory.run(stop, until_idle=True)      # until stop is set, or every order ends

``cellctl factory run`` runs it. Each tick it gives every queued order to the online cell
that makes its part type with the earliest estimated finish (:mod:`cellctl.factory.dispatch`:
by the cells' bounds, or by their own plans with ``[dispatch] estimate = "plan"``), logging
why, committing the choice before the order goes out; re-sends every order its cell has not
answered each ``resend`` seconds (orders are idempotent by id at the cell), with its due time
if it has one (``cellctl factory submit --due``); and puts back in
the queue an order its cell refused, or one a cell that went offline did not take before the
order's ``expires`` (``accept_timeout`` after it was sent: the cell refuses it after that, so it
is made by one cell). An order no cell can ever make fails, saying why
(:func:`~cellctl.factory.dispatch.stuck`): no cell of ``factory.toml`` makes its part type,
or every one that does refused it; one that waits for a cell to come back, or for a cell
never heard to say what it makes, waits. A cancel asked for an order at a cell
(:mod:`cellctl.factory.cancel`) goes to that cell instead of the order, again each
``resend`` until the cell answers. Reports, state and status come in on a persistent session and are
acknowledged to the broker only after they are committed to the store. A cell's reports are
taken in order (:mod:`cellctl.factory.store`); when some are missing the cell is asked for
them again (an :class:`~cellctl.mailbox.wire.AskMessage` on its orders topic). A message that
fails its model (:mod:`cellctl.mailbox.wire`) is logged with its topic and dropped: nothing
that arrives on a topic ends the controller.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
from collections.abc import Callable

import aiomqtt

from cellctl.clock import Clock, current_clock
from cellctl.factory.config import FactoryConfig
from cellctl.factory.dispatch import Estimating, choose, stuck
from cellctl.factory.store import (
    OPEN_STATES,
    QUEUED,
    SENT,
    CellSeen,
    FactoryOrder,
    FactoryStore,
)
from cellctl.mailbox.mqttlink import BACKOFF_S, MqttSettings, Reconnect
from cellctl.mailbox.wire import (
    AskMessage,
    CancelMessage,
    OrderMessage,
    WireError,
    parse_report,
    parse_state,
    parse_status,
)

#: How long the factory must have been connected before it moves an unanswered order from an
#: offline cell: reports the broker kept for it arrive first (a cell reconnects within the
#: longest backoff).
SETTLE_S = BACKOFF_S[1] + 1.0
#: The longest ``run --until-idle`` waits, once every order ended, for the cells' states
#: that follow their last reports (a cell's poll period, with room).
LAST_STATE_S = 10.0
#: Of a cell's messages dropped (malformed), how many are logged in full per window, and
#: the window, s: the rest are counted in one line.
IGNORED_TOLD = 5
IGNORED_WINDOW_S = 10.0
#: How often the store is looked at for orders submitted by another process.
SUBMIT_CHECK_S = 0.02


class FactoryController:
    """The factory's controller (see module docstring)."""

    def __init__(
        self,
        config: FactoryConfig,
        store: FactoryStore,
        *,
        log: Callable[[str], None] = lambda text: None,
        clock: Clock | None = None,
    ) -> None:
        self.config = config
        self.store = store
        self._log = log
        self._clock = clock
        self.connected_since: float | None = None
        self.listeners: list[Callable[[], None]] = []
        self._wake = asyncio.Event()
        self._prefix = {prefix: name for name, prefix in config.cells.items()}
        self._data_version = -1
        #: Per cell: (epoch, seq) after which its reports are missing, and when last asked.
        self._missing: dict[str, tuple[str, int]] = {}
        self._asked: dict[str, tuple[tuple[str, int], float]] = {}
        #: Per cell: when its window of dropped messages began, and how many it has.
        self._ignoring: dict[str, tuple[float, int]] = {}
        #: Per queued order, why it waits as last logged (once settled: not the moments
        #: before the cells' retained states come in).
        self._told_waiting: dict[str, str] = {}

    @property
    def clock(self) -> Clock:
        """What the factory reads the time from: the clock given, else the running loop's."""
        return self._clock or current_clock()

    def log(self, text: str, cell: str | None = None, order_id: str | None = None) -> None:
        self.store.log(text, cell, order_id)
        self._log(text)

    def poke(self) -> None:
        """Look at the store now (an order was submitted in this process)."""
        self._wake.set()

    # -- running --------------------------------------------------------------------------------

    async def run(self, stop: asyncio.Event, *, until_idle: bool = False) -> None:
        """Serve until ``stop`` is set (or, with ``until_idle``, every order has ended)."""
        # The factory has no prefix of its own: it speaks on the cells' (factory.toml).
        settings = MqttSettings.load(
            self.config.broker_url.rstrip("/") + "/factory", self.config.credentials, self.config.ca
        )
        self._reconnect = Reconnect(
            settings,
            stop,
            log=self.log,
            what="broker",
            errors=(aiomqtt.MqttError,),
            twin="another `cellctl factory run` of this factory, on another host",
        )
        await self._reconnect.run(
            lambda: self._session(settings, stop, until_idle), on_drop=self._dropped
        )

    def _dropped(self) -> None:
        self.connected_since = None

    async def _session(self, settings: MqttSettings, stop: asyncio.Event, until_idle: bool) -> None:
        ident = "cellctl-factory-" + "".join(
            c if c.isalnum() or c in "-_" else "-" for c in self.config.name
        )
        client = settings.client(ident)
        # Acknowledge a report only once it is committed: a factory killed between the two
        # gets it again from its persistent session.
        client._client.manual_ack_set(True)
        async with client:
            for prefix in self.config.cells.values():
                for topic in ("reports", "state", "status"):
                    await client.subscribe(f"{prefix}/{topic}", qos=1)
            self.connected_since = self.clock.now()
            self._reconnect.connected()
            self.log(f"{self.config.name}: connected to the broker {self.config.broker_url}")
            receiver = asyncio.create_task(self._receive(client))
            try:
                while not stop.is_set():
                    await self.tick(client)
                    if receiver.done():
                        receiver.result()  # the connection broke: raises its MqttError
                    if until_idle and self.idle():
                        await self._hear_the_last_states(stop)
                        return
                    await self._wait()
            finally:
                receiver.cancel()
                with contextlib.suppress(BaseException):
                    await receiver
                self.connected_since = None

    async def _wait(self) -> None:
        """Until poked, an order submitted elsewhere, or the poll period is over."""
        clock = self.clock
        deadline = clock.monotonic() + self.config.poll_period
        while clock.monotonic() < deadline:
            version = self.store.data_version()
            if version != self._data_version:
                self._data_version = version
                return
            with contextlib.suppress(TimeoutError):
                async with clock.timeout(min(SUBMIT_CHECK_S, deadline - clock.monotonic())):
                    await self._wake.wait()
            if self._wake.is_set():
                self._wake.clear()
                return

    async def _hear_the_last_states(self, stop: asyncio.Event) -> None:
        """Every order ended: wait (at most :data:`LAST_STATE_S`) until each online cell's
        state says it has no part open, so that what the factory keeps of the cells (``factory
        cells``) is not the state before their last part ended (a cell sends its state at
        most once its poll period, after the report)."""
        clock = self.clock
        deadline = clock.monotonic() + LAST_STATE_S
        while not stop.is_set() and clock.monotonic() < deadline:
            cells = self.store.cells().values()
            if all(c.status != "online" or not c.state.get("parts_open") for c in cells):
                return
            with contextlib.suppress(TimeoutError):
                async with clock.timeout(SUBMIT_CHECK_S * 5):
                    await stop.wait()

    def idle(self) -> bool:
        """No order is open (every one is done, failed or cancelled): an order no cell can
        ever make has failed; one that waits for a cell to come back keeps it open."""
        return not self.store.orders(OPEN_STATES)

    # -- in: reports, state, status -------------------------------------------------------------

    async def _receive(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            topic = message.topic.value
            try:
                payload = message.payload if isinstance(message.payload, bytes) else b""
                self.take(topic, payload)
            except Exception as e:  # nothing that arrives on a topic ends the controller
                self.log(f"{topic}: a message dropped: {e!r}"[:300])
            finally:
                if message.qos > 0:
                    client._client.ack(message.mid, message.qos)

    def take(self, topic: str, payload: bytes) -> None:
        """One message from a cell, committed to the store; one that fails its model is
        logged with its topic and why, and dropped."""
        prefix, _, kind = topic.rpartition("/")
        cell = self._prefix.get(prefix)
        if cell is None:
            return
        try:
            if kind == "status":
                status = parse_status(payload)
                if self.store.set_status(cell, status):
                    self._log(f"{cell} {status}")
                    self._changed()
            elif kind == "state":
                self.store.set_state(cell, parse_state(payload).model_dump(mode="json"))
                self._changed()
            elif kind == "reports":
                self._take_report(cell, topic, payload)
        except WireError as e:
            self._ignored(cell, f"{cell}: a {kind} message ignored ({topic}): {e.reason}")

    def _ignored(self, cell: str, text: str) -> None:
        """Log a message of ``cell``'s that was dropped: the first :data:`IGNORED_TOLD` of
        each :data:`IGNORED_WINDOW_S` in full, the rest counted and told in one line as the
        window ends (a cell sending thousands a second fills neither the log nor the store,
        nor keeps the factory from reading the other cells)."""
        now = self.clock.monotonic()
        since, count = self._ignoring.get(cell, (now, 0))
        if now - since >= IGNORED_WINDOW_S:
            self._tell_ignored(cell, now)
            since, count = now, 0
        self._ignoring[cell] = (since, count + 1)
        if count < IGNORED_TOLD:
            self.log(text, cell)

    def _tell_ignored(self, cell: str, now: float) -> None:
        """The count of ``cell``'s messages dropped untold in its window, if any (the
        window ends)."""
        since, count = self._ignoring.pop(cell, (now, 0))
        if count > IGNORED_TOLD:
            self.log(
                f"{cell}: {count - IGNORED_TOLD} more messages ignored in {now - since:.0f} s "
                f"(the first {IGNORED_TOLD} told above)",
                cell,
            )

    def _take_report(self, cell: str, topic: str, payload: bytes) -> None:
        report = parse_report(payload)
        taken = self.store.take_report(cell, report)
        if taken.text:
            self._log(taken.text)
        if taken.ask_after is not None:
            self._missing[cell] = (report.epoch, taken.ask_after)
            if taken.refused:
                self.log(f"{cell}: {taken.refused} ({topic}): asking again", cell)
        elif self._missing.get(cell, ("", 0))[0] != report.epoch or (
            report.seq > self._missing[cell][1]
        ):
            self._missing.pop(cell, None)
        self._changed()

    def _changed(self) -> None:
        self._wake.set()
        for listener in list(self.listeners):
            listener()

    # -- out: dispatch, re-send, redirect -------------------------------------------------------

    async def tick(self, client: aiomqtt.Client) -> None:
        """Dispatch queued orders, re-send unanswered ones, move those that cannot stay, ask
        cells for the reports that are missing."""
        now = self.clock.now()
        moment = self.clock.monotonic()
        for cell, (since, _) in list(self._ignoring.items()):
            if moment - since >= IGNORED_WINDOW_S:  # a flood that stopped: its count told
                self._tell_ignored(cell, moment)
        await self._ask(client, now)
        cells = self.store.cells()
        settled = self.settled(now)
        for order in self.store.orders([SENT]):
            assert order.cell is not None
            if order.cancelling:
                continue  # its cancel goes instead (below): the order is not sent again
            seen = cells.get(order.cell)
            offline = seen is None or seen.status != "online"
            if offline and settled and order.expires is not None and now > order.expires:
                self.store.requeue(
                    order.id,
                    order.cell,
                    f"went offline and did not take it within {self.config.accept_timeout:g} s",
                )
                self._log(f"order {order.id}: {order.cell} offline, not taken: sent elsewhere")
            elif order.last_send is None or now - order.last_send >= self.config.resend:
                await self._publish(client, order)
                self.store.resent(order.id)
        await self._cancel(client, cells, now)
        await self._dispatch(client, cells, now)

    def settled(self, now: float) -> bool:
        """Connected long enough that what the broker kept for the factory (the cells'
        retained states, reports in its session) has come, and cells that were reconnecting
        are back: only then is an order judged by what the cells said."""
        return self.connected_since is not None and now - self.connected_since >= SETTLE_S

    async def _cancel(self, client: aiomqtt.Client, cells: dict[str, CellSeen], now: float) -> None:
        """Send each cancel asked for an order at a cell, again each ``resend`` until the cell
        answers (its answer is a report: the order cancelled, or the cancel refused)."""
        for order in self.store.cancelling():
            if order.cell not in self.config.cells:
                continue  # at a cell factory.toml no longer names: nothing can reach it
            seen = cells.get(order.cell)
            offline = seen is None or seen.status != "online"
            late = order.expires is not None and now > order.expires
            if order.state == SENT and offline and late and self.settled(now):
                # Not taken in time, so that cell refuses it now (as a redirect relies on):
                # nothing of it will be made there.
                why = f"{order.cell} went offline and did not take it in time"
                if self.store.cancel_here(order.id, why):
                    self._log(f"order {order.id} cancelled: {why}")
                continue
            if order.cancel_sent is not None and now - order.cancel_sent < self.config.resend:
                continue
            message = CancelMessage(
                cancel="order",
                id=order.id,
                by=order.cancel_by or "factory",
                reason=order.cancel_reason or "",
                asked=order.cancel_asked or now,
            )
            topic = f"{self.config.cells[order.cell]}/orders"
            await client.publish(topic, message.model_dump_json(), qos=1)
            if order.cancel_sent is None:
                self._log(f"order {order.id}: cancel sent to {order.cell}")
            self.store.cancel_sent(order.id)

    async def _dispatch(
        self, client: aiomqtt.Client, cells: dict[str, CellSeen], now: float
    ) -> None:
        """Choose a cell for every queued order, commit all choices at once, then send."""
        planned = {o.id: o for o in self.store.orders(OPEN_STATES)}
        queued = [o for o in planned.values() if o.state == QUEUED]
        waiting = {o.id for o in queued}
        self._told_waiting = {k: v for k, v in self._told_waiting.items() if k in waiting}

        def work(o: FactoryOrder) -> float:
            return o.qty * max(
                (c.part_types.get(o.part_type, 0.0) for c in cells.values()), default=0
            )

        # Higher priority first; within one priority the largest first, so the small ones
        # even out what the large ones leave (a balanced split of the burst).
        how = Estimating(self.config.estimate, now, self.config.plan_age)
        choices: list[tuple[str, str]] = []
        whys: dict[str, str] = {}
        for order in sorted(queued, key=lambda o: (-o.priority, -work(o))):
            cell, why = choose(order, cells, list(planned.values()), how)
            if cell is None:
                why, never = stuck(order, cells, self.config.cells)
                settled = self.settled(now)
                if never and settled:
                    self.store.fail(order.id, why)
                    self._log(f"order {order.id} failed: {why}")
                    continue
                self.store.note(order.id, why)
                if settled and self._told_waiting.get(order.id) != why:
                    self._told_waiting[order.id] = why
                    self.log(f"order {order.id} waits: {why}", order_id=order.id)
                continue
            choices.append((order.id, cell))
            whys[order.id] = why
            planned[order.id] = dataclasses.replace(order, state=SENT, cell=cell)
        if not choices:
            return
        sent = self.store.send_many(choices, now + self.config.accept_timeout, whys)
        for order in sorted(sent, key=lambda o: (o.submitted, o.id)):  # the cells' FIFO
            await self._publish(client, order)
            self._log(f"order {order.id}: {whys[order.id]}")
            self._log(f"order {order.id} sent to {order.cell}")

    async def _publish(self, client: aiomqtt.Client, order: FactoryOrder) -> None:
        assert order.cell is not None
        message = OrderMessage(
            id=order.id,
            part_type=order.part_type,
            qty=order.qty,
            priority=order.priority,
            expires=order.expires,
            due=order.due,  # left out of the payload when None: the message it always was
        )
        topic = f"{self.config.cells[order.cell]}/orders"
        await client.publish(topic, message.model_dump_json(), qos=1)

    async def _ask(self, client: aiomqtt.Client, now: float) -> None:
        """Ask each cell whose reports are missing to send them again, once a ``resend``."""
        for cell, (epoch, after) in list(self._missing.items()):
            asked = self._asked.get(cell)
            if (
                asked is not None
                and asked[0] == (epoch, after)
                and now - asked[1] < self.config.resend
            ):
                continue
            self._asked[cell] = ((epoch, after), now)
            ask = AskMessage(ask="reports", epoch=epoch, after=after)
            await client.publish(f"{self.config.cells[cell]}/orders", ask.model_dump_json(), qos=1)
