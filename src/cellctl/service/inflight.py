"""The API server's sessions and calls in flight: what a WebSocket client has queued and
running, what closing waits for, and the JSON-RPC errors of a server's load.

:class:`InFlight` is the part of :class:`~cellctl.service.server.ApiServer` that stops it as
``cellctl run`` stops: the calls that must run to their end are waited for, said in the log,
and cut short (each said, audited ``cancelled``) only on a second Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import threading
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from cellctl.service.rpc import SERVER_BUSY

if TYPE_CHECKING:
    from starlette.websockets import WebSocket

    from cellctl.service.limits import ApiLimits, Listener
    from cellctl.service.methods import Caller
    from cellctl.service.status import CellStatus
    from cellctl.service.token import TokenEntry

#: Messages waiting for a slow client before it is dropped.
MAX_QUEUED = 2000
#: Seconds closing waits for what is left once the calls that must end have ended: reads
#: being cancelled, answers and close frames going out.
CLOSE_GRACE = 5.0


class Session:
    """One WebSocket client: its send queue, its calls in flight and whether it subscribed."""

    def __init__(self, ws: WebSocket, entry: TokenEntry) -> None:
        self.ws = ws
        self.entry = entry  # whose token opened it (checked again at each call)
        # Text to send, or the code to close with once what came before has gone.
        self.queue: asyncio.Queue[str | int] = asyncio.Queue(MAX_QUEUED)
        self.subscribed = False
        self.open = True
        self.ended = asyncio.Event()  # its handler has ended
        self.in_flight = 0  # its calls (a batch is one) not yet answered
        self.last: CellStatus | None = None  # the status this client holds
        self.abandoned: set[asyncio.Future[Any]] = set()  # its calls that end when it goes

    def send(self, message: dict[str, Any] | list[Any] | str) -> None:
        """Queue ``message`` (a dict, a batch's answers, or JSON text made once for all)."""
        if not self.open:
            return
        text = message if isinstance(message, str) else json.dumps(message, default=str)
        try:
            self.queue.put_nowait(text)
        except asyncio.QueueFull:
            self.open = False  # too slow to keep up: it is dropped, the cell is not slowed
            self.queue = asyncio.Queue(1)
            self.queue.put_nowait(1013)

    def finish(self, code: int) -> None:
        """Close the session with ``code`` once what is queued has been sent."""
        if not self.open:
            return
        self.open = False
        try:
            self.queue.put_nowait(code)
        except asyncio.QueueFull:
            self.queue = asyncio.Queue(1)
            self.queue.put_nowait(code)

    async def writer(self) -> None:
        while True:
            item = await self.queue.get()
            if isinstance(item, int):
                with contextlib.suppress(Exception):
                    await self.ws.close(item)
                return
            await self.ws.send_text(item)


@dataclass(frozen=True)
class Flight:
    """A call in flight, as closing sees it."""

    method: str
    who: str
    params: Any
    #: It ends with its client, and when the server stops (a read that touches no machine).
    cut: bool

    def __str__(self) -> str:
        machine = self.params.get("machine") if isinstance(self.params, dict) else None
        where = f" on {str(machine)[:40]}" if machine else ""
        return f"{self.method[:100]} by {self.who}{where}"


class InFlight:
    """The calls in flight: each session's and token's counted against their caps, and
    waited for as the server closes (see module docstring)."""

    _flights: dict[asyncio.Task[Any], Flight]
    calls: set[asyncio.Task[None]]  # every call running (closing waits for them)
    _token_calls: dict[str, int]  # calls in flight by token name
    _token_sessions: dict[str, int]  # WebSockets open by token name
    _refusals: Listener  # the log of refused handshakes, rate-limited
    _closing: bool
    limits: ApiLimits

    def _say(self, text: str) -> None:
        raise NotImplementedError

    def _refused(self, session: Session, requests: list[Any], *, batch: bool) -> bool:
        """Refuse ``requests`` (one, or a batch: one call in flight) if the session, or its
        token over all its sessions, has as many calls in flight as it may, or the server
        stops: each request with an id gets :data:`SERVER_BUSY`, at once (a batch's in one
        array)."""
        name = session.entry.name
        if self._closing:
            error = stopping_error()
        elif session.in_flight >= self.limits.calls_per_session:
            error = busy_error(
                "connection",
                self.limits.calls_per_session,
                f"refused: this connection has {calls_text(session.in_flight)} in flight, the "
                "most one connection may have: send more once answers have come",
            )
        elif self._token_calls.get(name, 0) >= self.limits.calls_per_token:
            error = busy_error(
                "token",
                self.limits.calls_per_token,
                f"refused: the token {name!r} has {calls_text(self._token_calls[name])} in "
                "flight over its connections, the most one token may have: send more once "
                "answers have come",
            )
        else:
            return False
        answers = [
            {"jsonrpc": "2.0", "id": r["id"], "error": error}
            for r in requests
            if isinstance(r, dict) and isinstance(r.get("id"), str | int | float)
        ]
        if answers:
            session.send(answers if batch else answers[0])
        return True

    def _open_session(self, name: str) -> dict[str, Any] | None:
        """Count a WebSocket of token ``name`` from its handshake on (handshakes at once
        cannot all pass the cap); the error to refuse it with instead, past
        ``sessions_per_token``. :meth:`_close_session` once it ends."""
        held = self._token_sessions.get(name, 0)
        if held >= self.limits.sessions_per_token:
            reason = (
                f"refused: the token {name!r} has {held} WebSocket connections open, the most "
                "one token may have ([api] sessions_per_token): close one first"
            )
            self._refusals.note("sessions", reason)
            return busy_error("sessions", self.limits.sessions_per_token, reason)
        self._token_sessions[name] = held + 1
        return None

    def _close_session(self, name: str) -> None:
        left = self._token_sessions.get(name, 1) - 1
        if left > 0:
            self._token_sessions[name] = left
        else:
            self._token_sessions.pop(name, None)

    def _spawn(self, session: Session, work: Coroutine[Any, Any, None]) -> None:
        # The calls run in a task kept by the server: a client that goes away does not cancel
        # one halfway through a machine's transaction. It counts against the session and its
        # token until it ends (an acting call whose client left, too).
        task = asyncio.create_task(work)
        name = session.entry.name
        session.in_flight += 1
        self._token_calls[name] = self._token_calls.get(name, 0) + 1
        self.calls.add(task)

        def ended(done: asyncio.Task[None]) -> None:
            self.calls.discard(done)
            session.in_flight -= 1
            left = self._token_calls.get(name, 1) - 1
            if left > 0:
                self._token_calls[name] = left
            else:
                self._token_calls.pop(name, None)

        task.add_done_callback(ended)

    @contextlib.contextmanager
    def _flight(self, method: str, caller: Caller, params: Any, *, cut: bool) -> Iterator[None]:
        """The current task runs ``method`` for ``caller`` while in the block (for closing)."""
        task = asyncio.current_task()
        if task is None:
            yield
            return
        self._flights[task] = Flight(method, caller.who, params, cut)
        try:
            yield
        finally:
            self._flights.pop(task, None)

    def _must_finish(self) -> dict[asyncio.Task[Any], Flight]:
        """The calls in flight that run to their end (not cut short by closing)."""
        return {t: f for t, f in self._flights.items() if not f.cut and not t.done()}

    async def _finish_calls(self) -> None:
        """Wait for the calls that must run to their end; cut them short on Ctrl-C or SIGTERM
        (a second one: the first stopped the controller), or when this wait is cancelled."""
        waiting = self._must_finish()
        if not waiting:
            return
        names = "; ".join(str(f) for f in waiting.values())
        self._say(
            f"stopping: waiting for the API calls in flight to end: {names} "
            "(Ctrl-C again to cut them short)"
        )
        abort = asyncio.Event()
        try:
            with stop_signals_calling(abort.set):
                while waiting and not abort.is_set():
                    aborted = asyncio.ensure_future(abort.wait())
                    try:
                        await asyncio.wait(
                            {*waiting, aborted}, timeout=1.0, return_when=asyncio.FIRST_COMPLETED
                        )
                    finally:
                        aborted.cancel()
                    waiting = self._must_finish()
        except asyncio.CancelledError:
            await self._cut_short(self._must_finish())
            raise
        if waiting:
            await self._cut_short(waiting)

    async def _cut_short(self, flights: dict[asyncio.Task[Any], Flight]) -> None:
        """Cancel ``flights`` (each audited ``cancelled`` by the dispatcher), saying each."""
        for task, flight in flights.items():
            self._say(
                f"{flight}: cut short before its end, as the API stopped; what it drove may be "
                "left halfway (a program part-sent): look at it before using it again"
            )
            task.cancel()
        if flights:
            await asyncio.wait(set(flights), timeout=CLOSE_GRACE)


def rpc_error(rid: Any, code: int, message: str) -> dict[str, Any]:
    return {"jsonrpc": "2.0", "id": rid, "error": {"code": code, "message": message}}


def calls_text(count: int) -> str:
    return f"{count} call" + ("" if count == 1 else "s")


def busy_error(reason: str, limit: int, message: str) -> dict[str, Any]:
    """The error object of a call refused for the server's load."""
    return {"code": SERVER_BUSY, "message": message, "data": {"reason": reason, "limit": limit}}


def stopping_error() -> dict[str, Any]:
    return {
        "code": SERVER_BUSY,
        "message": "refused: the API is stopping (its server is closing); call again once it runs",
        "data": {"reason": "stopping"},
    }


@contextlib.contextmanager
def stop_signals_calling(callback: Callable[[], object]) -> Iterator[None]:
    """Ctrl-C and SIGTERM call ``callback`` while in the block, where nobody else handles
    them (Python's defaults: the command's own handlers are gone by the time its API closes);
    then the handlers are as they were. Outside the main thread, nothing changes."""
    loop = asyncio.get_running_loop()
    installed: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            before = signal.getsignal(sig)
            if before not in (signal.default_int_handler, signal.SIG_DFL):
                continue  # someone's own handler (or an ignored signal): left alone
            with contextlib.suppress(ValueError, RuntimeError, NotImplementedError):
                loop.add_signal_handler(sig, callback)
                installed[sig] = before
    try:
        yield
    finally:
        for sig, before in installed.items():
            loop.remove_signal_handler(sig)
            with contextlib.suppress(ValueError, TypeError, OSError):
                signal.signal(sig, before)
