"""The DNC server: many controls from one process, each on its own link, held exclusively.

::

    server = DncServer(load_shop(Path("SHOP")))
    await server.start()             # opens every link under its owner locks; one task each
    server.status()["mill1"].activity   # Activity.IDLE ...
    await server.send("mill1", data, drip=True, progress=print)   # by hand, between requests
    await server.line("mill1").stop()   # from another task: the transfer in flight ends here
    await server.close()

Each machine's task listens for the control: a punched tape (DC2 ... DC4) is split into its
programs; the request program (:mod:`.request`) makes the control's *next read* receive the
program it names (read into memory, or drip-fed), every other program is kept as received
(:mod:`.store`). A transfer by hand (``dnc.send`` / ``dnc.drip`` / ``dnc.receive`` through the
API) waits until the machine's task is between two listens, so a transfer is never cut in two.
A link that fails is logged, shown on the machine's status, and opened again after
:data:`REOPEN_S`; the other machines go on. A transfer stopped by hand (``dnc.stop``) ends at
once, whoever started it: its caller gets :class:`TransferStopped`, the control is left
mid-read (the operator resets it), and the driver waits for the control's next DC1.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

from cellctl.clock import current_clock
from cellctl.drivers.state import StateStore
from cellctl.errors import CellctlError, LinkClosed, LinkTimeout, UsageError
from cellctl.kinds.iso_cnc.dnc.config import DncMachine, ShopConfig
from cellctl.kinds.iso_cnc.dnc.request import Request, parse_request
from cellctl.kinds.iso_cnc.dnc.store import ShopStore, o_name, read_program_file
from cellctl.kinds.iso_cnc.driver import IsoCncDriver
from cellctl.kinds.iso_cnc.tape import DC2, split_programs, unframe
from cellctl.link import TrafficLog

log = logging.getLogger(__name__)

#: Seconds between two looks at what the control sent (a punch's DC2).
LISTEN_S = 0.5
#: Bytes an idle line may gather without a DC2 before they are dropped (noise).
MAX_IDLE_BYTES = 65536
#: Seconds before a failed link is opened again.
REOPEN_S = 5.0
#: Seconds a request waits for the control to start its read before it lapses.
REQUEST_WAIT_S = 1800.0
#: Seconds a punch may take once started (DC2 ... DC4).
PUNCH_S = 3600.0
#: Seconds between two progress figures passed on (the driver gives five a second).
PROGRESS_S = 0.5
#: Events a machine keeps for the status.
EVENTS = 30
#: Seconds a transfer by hand may take in all.
TRANSFER_S = 24 * 3600.0
#: Seconds a stopped transfer may take to let go of its link.
STOP_S = 10.0
#: Chunks of traffic each machine keeps for ``traffic.tail`` (the console's traffic pane).
TRAFFIC_KEEP = 200
#: Seconds a machine's traffic is kept after a client last asked for it.
WATCH_S = 30.0

Progress = Callable[[dict[str, Any]], None]


class TransferStopped(CellctlError):
    """A transfer stopped by hand: the message says where it stood."""


class WatchedTraffic(TrafficLog):
    """A machine's last chunks both ways, kept only while a client looks at them
    (:meth:`watch`, called by ``traffic.tail``, within the last :data:`WATCH_S`): a shop of
    hundreds of links spends nothing on traffic nobody reads."""

    def __init__(self) -> None:
        super().__init__(None, keep=TRAFFIC_KEEP)
        self.until = 0.0

    def watch(self) -> None:
        """Keep what goes both ways for the next :data:`WATCH_S` seconds."""
        self.until = current_clock().now() + WATCH_S

    def record(self, label: str, direction: str, data: bytes, when: float) -> None:
        if when <= self.until:
            super().record(label, direction, data, when)


class Activity(enum.StrEnum):
    """What a DNC machine is doing."""

    IDLE = "idle"
    """Listening for the control (a punch, or a request)."""
    WAITING = "waiting for read"
    """A program is ready: the control's next read (READ / CYCLE START) receives it."""
    READING = "reading"
    """The control reads a program into its memory."""
    DRIP_FEEDING = "drip-feeding"
    """The control runs a program as it arrives."""
    PUNCHING = "punching"
    """The control punches a program to the server."""
    AWAITING_PUNCH = "waiting for punch"
    """Someone waits for the control's next punch (``cellctl dnc receive``)."""
    OFFLINE = "offline"
    """Its link is not open (failed; opened again in a few seconds)."""


@dataclass(frozen=True)
class MachineStatus:
    """One DNC machine's status (what the API, the console and the dashboard show)."""

    name: str
    activity: Activity = Activity.OFFLINE
    program: str | None = None
    phase: str = ""
    """Where a transfer stands: ``waiting`` (for the control's DC1), ``sending``, ``stopped``
    (a DC3), ``running`` (all sent, the control runs the rest), ``receiving``."""
    chars_done: int = 0
    chars_total: int = 0
    chars_per_s: float = 0.0
    buffer_stops: int = 0
    eta_s: float | None = None
    stall_s: float = 0.0
    """Seconds the machine waited for data during this drip-feed (as the driver reckons it)."""
    since: float = 0.0
    last: str = ""
    """The last thing done, in words (``received O1234 (812 chars)``)."""
    error: str = ""
    pending: str = ""
    """The request waiting for the control's read (``drip-feed O1234``), if any."""
    transfers: int = 0
    failures: int = 0


def _progress_dict(p: Any) -> dict[str, Any]:
    """A driver's TransferProgress as the API pushes it."""
    return {
        "phase": str(getattr(p, "phase", "")),
        "chars_sent": int(getattr(p, "chars_sent", 0)),
        "chars_total": int(getattr(p, "chars_total", 0)),
        "chars_per_s": float(getattr(p, "chars_per_s", 0.0)),
        "buffer_stops": int(getattr(p, "buffer_stops", 0)),
        "elapsed_s": float(getattr(p, "elapsed_s", 0.0)),
        "eta_s": getattr(p, "eta_s", None),
        # the driver's modelled stall (the axes waiting for a block), where it gives one
        "stall_s": float(getattr(p, "stall_s", 0.0) or getattr(p, "stalls_modelled_s", 0.0)),
    }


@dataclass
class DncLine:
    """One machine of the server: its config, driver, task and status."""

    config: DncMachine
    store: ShopStore
    state: StateStore
    trace: TrafficLog | None = None
    driver: Any = None
    status: MachineStatus = field(init=False)
    pending: Request | None = None
    pending_since: float = 0.0
    turn: asyncio.Lock = field(default_factory=asyncio.Lock)
    changed: Callable[[], None] = lambda: None
    events: deque[tuple[float, str]] = field(default_factory=lambda: deque(maxlen=EVENTS))
    punch_waiters: list[asyncio.Future[list[dict[str, Any]]]] = field(default_factory=list)
    transfer: asyncio.Task[Any] | None = None
    """The driver's read-in or drip-feed in flight (what :meth:`stop` cancels)."""
    stopping: str = ""
    """Why the transfer in flight is being stopped (set by :meth:`stop`)."""

    def __post_init__(self) -> None:
        self.status = MachineStatus(self.config.name)
        if self.trace is None:  # what traffic.tail shows: this machine's last chunks
            self.trace = WatchedTraffic()

    def _note(self, text: str) -> None:
        """Log ``text`` in the machine's log and keep it for the status' events."""
        self.store.log(self.name, text)
        self.events.append((current_clock().now(), f"{self.name}: {text}"))

    @property
    def name(self) -> str:
        return self.config.name

    def _set(self, **changes: Any) -> None:
        new = replace(self.status, **changes)
        if new != self.status:
            self.status = new
            self.changed()

    # -- the link ---------------------------------------------------------------------------

    async def open(self) -> None:
        """Open the control's link under its owner locks (MachineInUse naming the holder)."""
        self.driver = await IsoCncDriver.connect(
            self.config.url,
            name=self.name,
            settings=self.config.settings,
            store=self.state,
            options=self.config.options,
            trace=self.trace,
        )
        self._set(activity=Activity.IDLE, error="", since=current_clock().now())

    async def close(self) -> None:
        driver, self.driver = self.driver, None
        if driver is not None:
            await driver.close()
        self._set(activity=Activity.OFFLINE)

    # -- transfers --------------------------------------------------------------------------

    def _on_progress(self, forward: Progress | None) -> Callable[[Any], None]:
        last = [0.0]

        def progress(p: Any) -> None:
            d = _progress_dict(p)
            now = current_clock().monotonic()
            if now - last[0] < PROGRESS_S and d["phase"] not in ("done", "waiting", "stopped"):
                return  # many machines at once: two figures a second are enough
            last[0] = now
            if not d["stall_s"] and self.driver is not None:
                # the driver's modelled stall so far (the axes waiting for a block)
                d["stall_s"] = float(self.driver.host_status().stall_s)
            self._set(
                phase=d["phase"],
                chars_done=d["chars_sent"],
                chars_total=d["chars_total"],
                chars_per_s=d["chars_per_s"],
                buffer_stops=d["buffer_stops"],
                eta_s=d["eta_s"],
                stall_s=d["stall_s"],
            )
            if forward is not None:
                forward(d)

        return progress

    async def send(
        self,
        program: str,
        data: bytes,
        *,
        drip: bool,
        progress: Progress | None = None,
        timeout: float = TRANSFER_S,
    ) -> dict[str, Any]:
        """Send ``data`` (a program's text): into memory, or drip-fed; the control starts the
        read (it sends DC1). The caller holds :attr:`turn`."""
        if self.driver is None:
            raise LinkClosed(f"{self.name}: its link is not open ({self.status.error or 'closed'})")
        activity = Activity.DRIP_FEEDING if drip else Activity.READING
        self._set(
            activity=activity,
            program=program,
            phase="waiting",
            chars_done=0,
            chars_total=len(data),
            buffer_stops=0,
            stall_s=0.0,
            eta_s=None,
            since=current_clock().now(),
        )
        what = "drip-fed" if drip else "read in"
        method = self.driver.drip_feed if drip else self.driver.read_in
        # Its own task, so that stop() cancels the transfer and not whoever waits for it.
        self.transfer = asyncio.ensure_future(
            method(data, progress=self._on_progress(progress), timeout=timeout)
        )
        self.stopping = ""
        try:
            report = await self.transfer
        except asyncio.CancelledError:
            current = asyncio.current_task()
            if not self.stopping or (current is not None and current.cancelling()):
                raise  # the caller itself is cancelled (the server closes): not a stop
            self._note(self.stopping)
            self._set(activity=Activity.IDLE, last=self.stopping, error="")
            raise TransferStopped(self.stopping) from None
        except CellctlError as e:
            self._note(f"{program}: {what} FAILED: {e}")
            self._set(activity=Activity.IDLE, error=str(e), failures=self.status.failures + 1)
            raise
        finally:
            self.transfer = None
        number = _number(data)
        if number is not None:
            self.store.keep_sent(self.name, number, data)
        result = _progress_dict(report)
        seconds = result["elapsed_s"]
        message = (
            f"{program}: {what}, {len(data)} chars in {seconds:.1f} s, "
            f"{result['buffer_stops']} buffer stops"
        )
        if drip:  # the machine's wait for blocks the line had not brought yet
            message += f", stalled {result['stall_s']:.1f} s"
        self._note(message)
        self._set(
            activity=Activity.IDLE,
            last=message,
            error="",
            transfers=self.status.transfers + 1,
            failures=0,
        )
        return {"message": message, **result}

    async def stop(self, timeout: float = STOP_S) -> str:
        """Stop the read-in or drip-feed in flight (the control is left mid-read: its
        operator resets it), or drop the request waiting for the control's read; what was
        stopped, in words. UsageError when there is neither."""
        transfer = self.transfer
        if transfer is not None and not transfer.done():
            s = self.status
            what = "drip-feed" if s.activity is Activity.DRIP_FEEDING else "read-in"
            self.stopping = (
                f"{s.program}: {what} stopped by hand at {s.chars_done}/{s.chars_total} chars "
                "(reset the control before its next read)"
            )
            transfer.cancel()
            try:
                async with current_clock().timeout(timeout):
                    await asyncio.wait({transfer})
            except TimeoutError:
                said = f"{self.name}: the transfer did not stop within {timeout:g} s"
                raise LinkTimeout(said) from None
            if not transfer.cancelled():  # it ended on its own before the stop reached it
                return f"{s.program}: the {what} had ended: nothing to stop"
            return self.stopping
        if self.pending is not None:
            request, self.pending = self.pending, None
            message = f"request {request} dropped by hand"
            self._note(message)
            self._set(activity=Activity.IDLE, pending="", last=message)
            return message
        raise UsageError(
            f"{self.name}: no transfer in flight and no request waiting "
            f"(it is {self.status.activity.value})"
        )

    async def receive(self, *, timeout: float) -> list[dict[str, Any]]:
        """Take the punch the control has started (its DC2 is in): keep it, answer requests.
        The caller holds :attr:`turn`."""
        if self.driver is None:
            raise LinkClosed(f"{self.name}: its link is not open ({self.status.error or 'closed'})")
        data: bytes = await self.driver.receive(progress=self._on_progress(None), timeout=timeout)
        return self.take_punch(data)

    async def wait_punch(self, timeout: float) -> list[dict[str, Any]]:
        """What the control punches next, once the machine's task has taken it (kept,
        requests answered); LinkTimeout when nothing is punched within ``timeout``."""
        waiter: asyncio.Future[list[dict[str, Any]]] = asyncio.get_running_loop().create_future()
        self.punch_waiters.append(waiter)
        if self.status.activity is Activity.IDLE:
            self._set(activity=Activity.AWAITING_PUNCH)
        try:
            async with current_clock().timeout(timeout):
                return await waiter
        except TimeoutError:
            raise LinkTimeout(
                f"{self.name}: nothing punched in {timeout:g} s (select the program, press PUNCH)"
            ) from None
        finally:
            if waiter in self.punch_waiters:
                self.punch_waiters.remove(waiter)
            if not self.punch_waiters and self.status.activity is Activity.AWAITING_PUNCH:
                self._set(activity=Activity.IDLE)

    def take_punch(self, data: bytes) -> list[dict[str, Any]]:
        """Split a punched tape into programs: answer a request, keep the others."""
        now = current_clock().now()
        done: list[dict[str, Any]] = []
        for program in split_programs(unframe(data)):
            raw = program.text.encode("latin-1", "replace")
            try:
                request = parse_request(program.number, program.text, self.config.request)
            except UsageError as e:
                kept = self.store.keep_received(self.name, program.number, raw, now)
                self._note(f"request refused: {e}; kept as {kept.path.name}")
                self._set(last=f"request refused: {e}", error=str(e))
                done.append({"program": program.number, "refused": str(e), "kept": str(kept.path)})
                continue
            if request is not None:
                done.append(self._request(request))
                continue
            kept = self.store.keep_received(self.name, program.number, raw, now)
            message = f"received {o_name(program.number)} ({len(raw)} chars) as {kept.path.name}"
            self._note(message)
            self._set(last=message)
            done.append({"program": program.number, "kept": str(kept.path), "chars": len(raw)})
        waiters, self.punch_waiters = self.punch_waiters, []
        for waiter in waiters:
            if not waiter.done():
                waiter.set_result(done)
        return done

    def _request(self, request: Request) -> dict[str, Any]:
        try:
            path = self.store.program(self.name, request.program)
        except UsageError as e:
            self._note(f"request {request} refused: {e}")
            self._set(last=f"request {request} refused", error=str(e))
            return {"request": str(request), "refused": str(e)}
        self.pending, self.pending_since = request, current_clock().now()
        message = f"request: {request} ({path.name}) on the control's next read"
        self._note(message)
        self._set(activity=Activity.WAITING, pending=str(request), last=message, error="")
        return {"request": str(request), "file": str(path)}

    async def answer(self) -> None:
        """Send the pending request's program when the control reads (the caller holds
        :attr:`turn`); a request older than :data:`REQUEST_WAIT_S` lapses."""
        request = self.pending
        assert request is not None
        if current_clock().now() - self.pending_since > REQUEST_WAIT_S:
            self.pending = None
            self._note(f"request {request} lapsed: the control did not read")
            self._set(activity=Activity.IDLE, pending="")
            return
        try:
            path = self.store.program(self.name, request.program)
            data = read_program_file(path)
        except UsageError as e:
            self.pending = None
            self._note(f"request {request} dropped: {e}")
            self._set(activity=Activity.IDLE, pending="", error=str(e))
            return
        self.pending = None
        self._set(pending="")
        await self.send(path.name, data, drip=request.drip, timeout=TRANSFER_S)

    # -- the machine's task -----------------------------------------------------------------

    async def run(self) -> None:
        """Listen for the control forever: punches kept, requests answered, links reopened.

        It looks at what the link has received (without taking it) every :data:`LISTEN_S`:
        a DC2 starts a punch, taken whole; between two looks a transfer by hand has the link.
        """
        while True:
            try:
                if self.driver is None:
                    await self.open()
                async with self.turn:
                    await self._look()
                await current_clock().sleep(LISTEN_S)
            except asyncio.CancelledError:
                raise
            except TransferStopped:
                pass  # a request's answer stopped by hand: noted already
            except LinkClosed as e:
                await self._failed(e, reopen=True)
            except CellctlError as e:
                await self._failed(e, reopen=self.driver is None)

    async def _look(self) -> None:
        link = self.driver.link
        if link.closed:
            raise LinkClosed(f"{self.name}: the link closed")
        if self.pending is not None:
            await self.answer()
        elif DC2 in link.pending():
            self._set(
                activity=Activity.PUNCHING, program=None, phase="", chars_done=0, chars_total=0
            )
            try:
                await self.receive(timeout=PUNCH_S)
            finally:
                after = Activity.AWAITING_PUNCH if self.punch_waiters else Activity.IDLE
                self._set(activity=Activity.WAITING if self.pending else after)
        elif len(link.pending()) > MAX_IDLE_BYTES:
            link.reset_input()  # noise on an idle line: nothing waits for it

    async def _failed(self, e: CellctlError, *, reopen: bool) -> None:
        self._note(f"error: {e}")
        log.warning("%s: %s", self.name, e)
        self._set(error=str(e), failures=self.status.failures + 1)
        if reopen:
            with contextlib.suppress(CellctlError):
                await self.close()
            self._set(activity=Activity.OFFLINE, error=str(e))
            await current_clock().sleep(REOPEN_S)


def _number(data: bytes) -> int | None:
    programs = split_programs(unframe(data))
    return programs[0].number if programs else None


class DncServer:
    """The machines of one shop, each on its own task (see module docstring)."""

    def __init__(self, config: ShopConfig, *, trace: TrafficLog | None = None) -> None:
        self.config = config
        self.store = ShopStore(config.root)
        self.state = StateStore(config.root)
        self.listeners: list[Callable[[], None]] = []
        self.started = current_clock().now()
        self.lines = {
            name: DncLine(m, self.store, self.state, trace=trace, changed=self._changed)
            for name, m in config.machines.items()
        }
        self._tasks: list[asyncio.Task[None]] = []

    def _changed(self) -> None:
        for listener in self.listeners:
            listener()

    def line(self, name: str) -> DncLine:
        found = self.lines.get(name)
        if found is None:
            known = ", ".join(sorted(self.lines))
            raise UsageError(f"unknown DNC machine {name!r} (known: {known})")
        return found

    async def start(self) -> None:
        """Open every machine's link (all refused if one is owned elsewhere), then serve."""
        opened: list[DncLine] = []
        try:
            for line in self.lines.values():
                self.store.machine(line.name)
                await line.open()
                opened.append(line)
        except BaseException:
            for line in opened:
                with contextlib.suppress(CellctlError):
                    await line.close()
            raise
        self._tasks = [asyncio.create_task(line.run()) for line in self.lines.values()]

    async def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, CellctlError):
                await task
        self._tasks = []
        for line in self.lines.values():
            with contextlib.suppress(CellctlError):
                await line.close()

    def status(self) -> dict[str, MachineStatus]:
        return {name: line.status for name, line in self.lines.items()}
