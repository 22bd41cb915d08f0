"""One DNC machine on its own link, held exclusively: :class:`DncLine` listens for the
control (a punch, a request), answers its next read, and runs a transfer by hand between two
listens. :class:`~cellctl.kinds.iso_cnc.dnc.server.DncServer` holds one per machine (see its
module for how a shop is served, and how a transfer ends when stopped).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

from cellctl.clock import current_clock
from cellctl.drivers.state import StateStore
from cellctl.errors import (
    CellctlError,
    LinkClosed,
    LinkError,
    LinkTimeout,
    MachineInUse,
    UsageError,
)
from cellctl.kinds.iso_cnc.dnc.config import DncMachine
from cellctl.kinds.iso_cnc.dnc.punched import take_punch
from cellctl.kinds.iso_cnc.dnc.request import Request
from cellctl.kinds.iso_cnc.dnc.status import (
    UNTHROTTLED,
    Activity,
    MachineStatus,
    TransferStopped,
    WatchedTraffic,
    all_out_words,
    ended_words,
    offline_words,
    online_words,
    progress_dict,
    started_words,
    state_words,
)
from cellctl.kinds.iso_cnc.dnc.store import (
    ShopStore,
    check_program_number,
    program_chars,
    read_program_file,
)
from cellctl.kinds.iso_cnc.driver import IsoCncDriver, ReadNotStarted
from cellctl.kinds.iso_cnc.tape import DC2, split_programs, unframe
from cellctl.kinds.iso_cnc.transfer import with_words
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
#: Seconds a punch under way may go silent before it is taken as ended without its DC4: a
#: control punches without a pause, so silence is PUNCH stopped at the control or a cable
#: pulled (the machine would otherwise show "punching" until PUNCH_S).
PUNCH_IDLE_S = 10.0
#: Seconds between two progress figures passed on (the driver gives five a second).
PROGRESS_S = 0.5
#: Events a machine keeps for the status.
EVENTS = 30
#: Seconds a transfer by hand may take in all.
TRANSFER_S = 24 * 3600.0
#: Seconds a stopped transfer may take to let go of its link.
STOP_S = 10.0

Progress = Callable[[dict[str, Any]], None]


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
    ticket: str | None = None
    """The caller's name for the transfer in flight (it may stop that one only)."""
    claimed: str = ""
    """A transfer by hand about to start (see :meth:`claim`)."""
    claimed_ticket: str | None = None
    """The ticket of the transfer claimed."""
    cancelled: str = ""
    """Why the transfer claimed was stopped before it began (its send() then sends nothing)."""
    tape_out: asyncio.Event = field(default_factory=asyncio.Event)
    """Set once the transfer in flight has all of its tape (or its clean end) out."""
    stop_command: str = ""
    """The command that stops this machine's transfer, as a busy refusal suggests it
    (``cellctl dnc stop mill1 --dir /srv/shop5``: see ``ShopConfig.command``)."""
    retries: bool = True
    """False for a one-shot command's machine: a link lost is said without "tried again"
    (the command ends with its transfer; nothing would try)."""

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
        if self.status.activity is Activity.OFFLINE and self.status.error:
            # back from offline (logged once as such): said beside it, in the same words
            self._note(online_words(self.name, self.config.url))
        self._set(activity=Activity.IDLE, error="", since=current_clock().now())

    async def close(self) -> None:
        driver, self.driver = self.driver, None
        if driver is not None:
            await driver.close()
        self._set(activity=Activity.OFFLINE)

    def _down(self, what: str) -> LinkClosed:
        why = self.status.error or f"{self.name}: offline"
        return LinkClosed(f"{why}: its link is down: {what} until it is back")

    def require_link(self, what: str) -> None:
        """LinkClosed, in words, when the machine's link is down (offline): ``what`` cannot
        be done (``nothing can be punched to the server``) until it is back."""
        if self.driver is None:
            raise self._down(what)

    # -- transfers --------------------------------------------------------------------------

    def _on_progress(self, forward: Progress | None) -> Callable[[Any], None]:
        last = [0.0]

        def progress(p: Any) -> None:
            d = progress_dict(p)
            if d["phase"] in ("running", "done"):
                self.tape_out.set()  # all of the tape (or its clean end) is out
            if d["phase"] == "done" and not self.stopping:
                # The control ended the read at the closing %: the rest of the trailer (tape
                # feed) never goes out. The tape was what went: a bar ends at its total. (A
                # tape ended early keeps its total: where it ended is said of it.)
                d["chars_total"] = d["chars_sent"]
            now = current_clock().monotonic()
            if now - last[0] < PROGRESS_S and d["phase"] not in UNTHROTTLED:
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

    def busy(self) -> str:
        """What the machine is doing that a second transfer would have to wait for, in
        words (``reading O1001.nc``); empty when it is free."""
        s = self.status
        if s.activity in (Activity.READING, Activity.DRIP_FEEDING, Activity.WAITING):
            return state_words(s)
        if s.activity is Activity.PUNCHING:
            return "punching"
        return self.claimed  # about to start (waiting for the machine's turn)

    @contextlib.contextmanager
    def claim(self, what: str, ticket: str | None = None) -> Iterator[None]:
        """Hold the machine for a transfer by hand (``what``: ``read-in of O1234.nc``) from
        now until the block ends; MachineInUse at once, naming what it does and how to stop
        it, when it is busy. Taken before waiting for :attr:`turn`, so two callers never both
        wait for it; a stop meanwhile cancels it (:meth:`send` then sends nothing)."""
        doing = self.busy()
        if doing:
            stop = self.stop_command or f"cellctl dnc stop {self.name}"
            raise MachineInUse(
                f"{self.name} is busy: {doing}; wait for it to end, or stop it with `{stop}`"
            )
        self.claimed, self.claimed_ticket, self.cancelled = what, ticket, ""
        try:
            yield
        finally:
            self.claimed, self.claimed_ticket, self.cancelled = "", None, ""

    async def send(
        self,
        program: str,
        data: bytes,
        *,
        drip: bool,
        progress: Progress | None = None,
        timeout: float | None = None,
        ticket: str | None = None,
        by_hand: bool = False,
        lapse: str = "",
    ) -> dict[str, Any]:
        """Send ``data`` (a program's text): into memory, or drip-fed; the control starts the
        read (it sends DC1). The caller holds :attr:`turn`. ``ticket``: the caller's own
        name for it, with which it may stop it (``dnc.stop``) and nothing else. ``by_hand``:
        a transfer a user started (``dnc send``, the console, the API), whose start the log
        says as it says its end (a request's is the request's own line). ``timeout``: the
        wait for the control's DC1 (the machine's ``options.dc1_timeout`` by default);
        ``lapse``: what a wait that ran out is (a request's lapse), instead of a failure."""
        if self.cancelled:  # stopped while it waited for the machine's turn
            said, self.cancelled = self.cancelled, ""
            self._note(said)
            self._set(last=said)
            raise TransferStopped(said)
        self.require_link("nothing can be sent to it")
        if by_hand:  # taken: its end (done, failed, stopped) is logged below
            self._note(started_words(program, drip, program_chars(data)))
        activity = Activity.DRIP_FEEDING if drip else Activity.READING
        self._set(  # "waiting" once the driver has checked and framed it (its tape's size)
            activity=activity,
            program=program,
            phase="preparing",
            chars_done=0,
            chars_total=0,
            buffer_stops=0,
            stall_s=0.0,
            eta_s=None,
            since=current_clock().now(),
        )
        what = "drip-fed" if drip else "read in"
        method = self.driver.drip_feed if drip else self.driver.read_in
        self.stopping, self.ticket, self.tape_out = "", ticket, asyncio.Event()
        # Its own task, so that stop() cancels the transfer and not whoever waits for it.
        self.transfer = asyncio.ensure_future(
            method(
                data,
                progress=self._on_progress(progress),
                timeout=timeout,
                name=program.rsplit(".", 1)[0],
            )
        )
        try:
            report = await self.transfer
        except asyncio.CancelledError:
            current = asyncio.current_task()
            if not self.stopping or (current is not None and current.cancelling()):
                raise  # the caller itself is cancelled (the server closes): not a stop
            self._note(self.stopping)
            self._set(activity=Activity.IDLE, last=self.stopping, error="")
            raise TransferStopped(self.stopping) from None
        except ReadNotStarted as e:
            if not lapse:
                self._note(f"{program}: {what} FAILED: {e}")
                self._set(activity=Activity.IDLE, error=str(e), failures=self.status.failures + 1)
                raise
            self._note(lapse)
            self._set(activity=Activity.IDLE, last=lapse, error="")
            raise TransferStopped(lapse) from None
        except CellctlError as e:
            end = self.driver.ended_at
            # Where the tape ended, as a stop says it: an integrator goes on from there.
            failed = e if end is None else with_words(e, end.words(drip=drip))
            self._note(f"{program}: {what} FAILED: {failed}")
            self._set(activity=Activity.IDLE, error=str(failed), failures=self.status.failures + 1)
            if failed is e:
                raise
            raise failed from e
        finally:
            self.transfer, self.ticket = None, None
        result = progress_dict(report)
        if report.ended_early:  # end_tape(): the rest of a block and % went out, no more
            self.stopping = ended_words(
                self.stopping or "stopped", program, drip, report.chars_sent, report.chars_total
            )
            self._note(self.stopping)
            self._set(activity=Activity.IDLE, last=self.stopping, error="")
            raise TransferStopped(self.stopping)
        number = _number(data)
        if number is not None:
            self.store.keep_sent(self.name, number, data)
        seconds = result["elapsed_s"]
        # What the control stores (its blocks, no %, CR or NUL), then the tape on the line.
        message = (
            f"{program}: {what}, {program_chars(data)} characters of program in "
            f"{seconds:.1f} s ({report.chars_sent} tape characters on the line), "
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

    async def stop(
        self, *, ticket: str | None = None, why: str = "stopped by hand", timeout: float = STOP_S
    ) -> str:
        """Stop the read-in or drip-feed in flight, or drop the request waiting for the
        control's read; what became of it, in words. A read that has begun is ended the
        clean way (the rest of its block, then ``%``: the control leaves the read, a
        drip-feed after the blocks it holds); one the control has not begun is cancelled
        (nothing went out). ``ticket``: stop only the transfer sent with it. Nothing to
        stop is said so."""
        transfer = self.transfer
        if transfer is not None and not transfer.done():
            if ticket is not None and ticket != self.ticket:
                raise UsageError(f"{self.name}: its transfer is not the one to stop")
            return await self._end(transfer, why, timeout)
        if self.claimed and (ticket is None or ticket == self.claimed_ticket):
            # taken, not begun (it waits for the machine's turn): it will send nothing
            self.cancelled = (
                f"{why}: the {self.claimed} was cancelled before the control began its read "
                "(nothing was sent)"
            )
            return self.cancelled
        if self.pending is not None and ticket is None:
            request, self.pending = self.pending, None
            message = f"request {request} dropped {why}"
            self._note(message)
            self._set(activity=Activity.IDLE, pending="", last=message)
            return message
        if ticket is not None:
            return f"{self.name}: the transfer had ended: nothing to stop"
        return (
            f"{self.name}: nothing to stop: no transfer in flight and no request waiting "
            f"(it is {state_words(self.status)})"
        )

    async def _end(self, transfer: asyncio.Future[Any], why: str, timeout: float) -> str:
        s = self.status
        drip = s.activity is Activity.DRIP_FEEDING
        what = f"{'drip-feed' if drip else 'read-in'} of {s.program}"
        where = self.driver.end_tape() if self.driver is not None else "waiting"
        if where == "out":
            said = all_out_words(what, drip)
            self._note(said)  # a stopper waiting on this log learns it changed nothing
            return f"{self.name}: {said}"
        self.stopping = why
        if where == "waiting":  # no DC1 yet: nothing went out, the read is simply not offered
            self.stopping = f"{why}: the {what} was cancelled before the control began its read"
            self.stopping += " (nothing was sent)"
            transfer.cancel()
        out = asyncio.ensure_future(self.tape_out.wait())
        try:  # the rest of a block and % under the control's flow control, then its DC3
            async with current_clock().timeout(timeout):
                await asyncio.wait({transfer, out}, return_when=asyncio.FIRST_COMPLETED)
        except TimeoutError:
            transfer.cancel()
            said = (
                f"the control did not take the end of the {what} within {timeout:g} s (it "
                "held DC3): the read is left open: reset the control before its next read"
            )
            self.stopping = f"{why}: {said}"
            raise LinkTimeout(f"{self.name}: {said}") from None
        finally:
            out.cancel()
        if where == "waiting":
            return self.stopping
        if transfer.done() and not transfer.cancelled() and transfer.exception() is None:
            report = transfer.result()
            return ended_words(why, s.program or "", drip, report.chars_sent, report.chars_total)
        if transfer.done():
            return f"{why}: the {what} ended: {self.status.error or self.status.last}"
        s = self.status  # a drip-feed whose end is out: the control runs what it holds
        return ended_words(why, s.program or "", drip, s.chars_done, s.chars_total, running=True)

    async def receive(self, *, timeout: float) -> list[dict[str, Any]]:
        """Take the punch the control has started (its DC2 is in): keep it, answer requests.
        The caller holds :attr:`turn`."""
        self.require_link("nothing can be received from it")
        data: bytes = await self.driver.receive(
            progress=self._on_progress(None), timeout=timeout, idle=PUNCH_IDLE_S
        )
        return await self.take_punch(data)

    async def wait_punch(self, timeout: float) -> list[dict[str, Any]]:
        """What the control punches next, once the machine's task has taken it (kept,
        requests answered); LinkTimeout when nothing is punched within ``timeout``."""
        self.require_link("nothing can be punched to the server")
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
        except asyncio.CancelledError:
            # The API cancels the wait when its client goes (the finally frees the machine),
            # and as it closes: one told its end first (the server stopping) says that.
            if not waiter.done() or waiter.cancelled() or (task := asyncio.current_task()) is None:
                raise
            task.uncancel()
            return waiter.result()
        finally:
            if waiter in self.punch_waiters:
                self.punch_waiters.remove(waiter)
            if not self.punch_waiters and self.status.activity is Activity.AWAITING_PUNCH:
                self._set(activity=Activity.IDLE)

    def end_punch_wait(self, why: str) -> str:
        """End the waits for a punch that has not begun (``dnc receive``), each told ``why``
        (a punch under way is taken whole, as ever); what was ended, in words, or ``""``."""
        waiting = [w for w in self.punch_waiters if not w.done()]
        if not waiting or self.status.activity is Activity.PUNCHING:
            return ""
        said = f"{why}: the wait for {self.name}'s punch ended (nothing was punched)"
        self.punch_waiters = []
        for waiter in waiting:
            waiter.set_exception(TransferStopped(said))
        self._note(said)
        return said

    async def take_punch(self, data: bytes) -> list[dict[str, Any]]:
        """Split a punched tape into programs: answer a request, keep the others
        (:func:`~cellctl.kinds.iso_cnc.dnc.punched.take_punch`)."""
        return await take_punch(self, data)

    async def answer(self) -> None:
        """Send the pending request's program when the control reads (the caller holds
        :attr:`turn`); a request older than :data:`REQUEST_WAIT_S` lapses."""
        request = self.pending
        assert request is not None
        lapsed = f"request {request} lapsed: the control did not read it within {_wait_words()}"
        left = REQUEST_WAIT_S - (current_clock().now() - self.pending_since)
        if left <= 0:
            self.pending = None
            self._note(lapsed)
            self._set(activity=Activity.IDLE, pending="", last=lapsed)
            return
        try:
            path = self.store.program(self.name, request.program, self.config.options.o_digits)
            data = read_program_file(path)
            check_program_number(path.name, data)
        except UsageError as e:
            self.pending = None
            self._note(f"request {request} dropped: {e}")
            self._set(activity=Activity.IDLE, pending="", error=str(e))
            return
        self.pending = None
        self._set(pending="")
        # The wait for the control's read is what is left of the request's time.
        await self.send(path.name, data, drip=request.drip, timeout=left, lapse=lapsed)

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
            except CellctlError as e:
                self._punch_failed(e)
                if isinstance(e, LinkClosed):
                    raise  # offline, and opened again
            finally:
                after = Activity.AWAITING_PUNCH if self.punch_waiters else Activity.IDLE
                self._set(activity=Activity.WAITING if self.pending else after)
        elif len(link.pending()) > MAX_IDLE_BYTES:
            link.reset_input()  # noise on an idle line: nothing waits for it

    def _punch_failed(self, e: CellctlError) -> None:
        """A punch that ended without its DC4 (silence, the link lost, an alarm): logged
        with what had come, and a ``dnc receive`` waiting for it is told so, not that
        nothing came."""
        came = self.status.chars_done if self.driver is None else self.driver.punched
        failed = f"punch FAILED after {came} characters"
        again = "nothing kept: press PUNCH on the control again"
        said = f"{failed}: {e}; {again}"
        self._note(said)
        self._set(error=said, failures=self.status.failures + 1)
        # Its own type (exit code): a link's error in these words, an alarm with them after.
        told = type(e)(said) if isinstance(e, LinkError) else with_words(e, f"{failed}; {again}")
        waiters, self.punch_waiters = self.punch_waiters, []
        for waiter in waiters:
            if not waiter.done():
                waiter.set_exception(told)

    async def _failed(self, e: CellctlError, *, reopen: bool) -> None:
        retry_s = REOPEN_S if self.retries else None
        said = offline_words(self.name, e, retry_s) if reopen else str(e)
        if said != self.status.error:  # a link that stays dead is logged once, not every 5 s
            self._note(f"error: {said}")
            log.warning("%s", said)
        self._set(error=said, failures=self.status.failures + 1)
        if reopen:
            with contextlib.suppress(CellctlError):
                await self.close()
            self._set(activity=Activity.OFFLINE, error=said)
            waiters, self.punch_waiters = self.punch_waiters, []
            for waiter in waiters:  # a `dnc receive` waiting: told now, not at its timeout
                if not waiter.done():
                    waiter.set_exception(self._down("nothing can be punched to the server"))
            await current_clock().sleep(REOPEN_S)


def _wait_words() -> str:
    """:data:`REQUEST_WAIT_S` in words (``30 minutes``)."""
    minutes = REQUEST_WAIT_S / 60
    return f"{minutes:g} minutes" if minutes >= 1 else f"{REQUEST_WAIT_S:g} s"


def _number(data: bytes) -> int | None:
    programs = split_programs(unframe(data))
    return programs[0].number if programs else None
