"""One clock for cellctl: real time, or virtual time that jumps when everything waits.

Code that waits or reads the time takes a :class:`Clock` (or asks :func:`current_clock` for
the running loop's) instead of calling ``time.*`` or ``loop.time()`` itself::

    clock = current_clock()                 # RealClock, or the virtual loop's VirtualClock
    started = clock.monotonic()
    async with clock.timeout(5.0):          # raises TimeoutError after 5 s of *this* clock
        await clock.sleep(1.0)
    stamp = clock.now()                     # wall time (unix seconds) for journals and logs

Run a coroutine on virtual time, where an hour of waiting takes a few milliseconds::

    result = run_virtual(main(), start=datetime(2026, 11, 27, 8, 0))

The same code runs on both: ``asyncio.sleep``, ``asyncio.timeout`` and ``loop.call_at``
already follow the virtual loop, because it is the loop's own time that jumps.
(``asyncio.wait_for`` would too, but ruff bans it: on 3.11 it can swallow a cancellation.)

Rules of the virtual loop (:class:`VirtualLoop`):

- Time jumps straight to the next timer when no callback is ready, no file descriptor of its
  own is ready, and nothing outside the loop can still bring work: no real file descriptor is
  registered and no executor job (``run_in_executor``, ``asyncio.to_thread``, ``getaddrinfo``)
  is outstanding. A jump never skips a timer: it lands on the earliest one.
- Real I/O is refused by default: registering a socket, pipe or pty (a TCP connection, a
  server, a subprocess, ``add_reader``) raises :class:`~cellctl.errors.UsageError`, because
  time would jump past the moment a real peer answers. In-process links (``mem://``) carry
  no file descriptor and are what a virtual run uses.
- ``VirtualLoop(allow_real_io=True)`` takes real I/O instead: while any real descriptor is
  registered (or an executor job runs), the loop waits in real time as a normal loop does and
  its time moves by the real time that passed; it jumps again once they are all gone.
- When every task waits and neither a timer nor anything outside can wake them, a real loop
  would hang for ever; the virtual one raises :class:`VirtualTimeStalled` naming the waiting
  tasks.
- Threads that call back into the loop other than through its executor
  (``call_soon_threadsafe`` from a thread of their own) are outside these rules.

``time_scale`` is how many seconds of machine time pass per second of the clock: an emulator
divides its machine times by it. Real time runs the emulated machines faster than life with a
scale above 1; virtual time needs no scale (1: the machines' own times, on a clock that jumps).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import selectors
import time
from collections.abc import Callable, Coroutine, Mapping
from datetime import datetime
from typing import Any, Protocol, TypeVar, TypeVarTuple, runtime_checkable

from cellctl.errors import CellctlError, UsageError

T = TypeVar("T")
Ts = TypeVarTuple("Ts")

#: Where a virtual loop's monotonic time starts (arbitrary, like ``time.monotonic()``'s origin;
#: far from 0 so that code taking 0.0 for "never" stays right).
VIRTUAL_ORIGIN = 1_000_000.0

# asyncio's longest select() wait: a timer further away than this makes a jump of this size.
_MAX_SELECT_S = 24 * 3600.0


class VirtualTimeStalled(CellctlError):
    """Every task of a virtual-time loop waits for something no timer or I/O can bring."""


@runtime_checkable
class Clock(Protocol):
    """What cellctl reads the time from and waits on (see the module docstring)."""

    @property
    def time_scale(self) -> float:
        """Seconds of machine time per second of this clock (emulators divide by it)."""
        ...

    def now(self) -> float:
        """Wall time, unix seconds: for journals, reports and logs, never for deadlines."""
        ...

    def monotonic(self) -> float:
        """Monotonic seconds, the event loop's own time: for deadlines and durations."""
        ...

    async def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of this clock."""
        ...

    def timeout(self, seconds: float | None) -> asyncio.Timeout:
        """``async with clock.timeout(s):`` raises TimeoutError after ``s`` (None: never)."""
        ...

    def call_at(
        self, when: float, callback: Callable[..., object], *args: Any
    ) -> asyncio.TimerHandle:
        """Call ``callback(*args)`` at ``when`` (a :meth:`monotonic` time) on the loop."""
        ...


def _scale(time_scale: float) -> float:
    if not time_scale > 0 or time_scale == float("inf"):
        raise UsageError(f"time scale must be a positive number, not {time_scale}")
    return float(time_scale)


class RealClock:
    """The wall clock and the standard event loop's time (``time.monotonic``)."""

    def __init__(self, time_scale: float = 1.0) -> None:
        self._time_scale = _scale(time_scale)

    @property
    def time_scale(self) -> float:
        return self._time_scale

    def now(self) -> float:
        return time.time()

    def monotonic(self) -> float:
        # The standard loop's time() is time.monotonic(): deadlines taken here suit call_at.
        return time.monotonic()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(seconds)

    def timeout(self, seconds: float | None) -> asyncio.Timeout:
        return asyncio.timeout(seconds)

    def call_at(
        self, when: float, callback: Callable[..., object], *args: Any
    ) -> asyncio.TimerHandle:
        return asyncio.get_running_loop().call_at(when, callback, *args)

    def __repr__(self) -> str:
        return f"RealClock(time_scale={self._time_scale:g})"


#: The real clock at scale 1, what code gets when no virtual loop runs.
REAL_CLOCK = RealClock()


class VirtualClock:
    """The clock of one :class:`VirtualLoop`: its time is the loop's, its wall time follows."""

    def __init__(self, loop: VirtualLoop, wall_start: float, time_scale: float = 1.0) -> None:
        self._loop = loop
        self._wall_offset = wall_start - VIRTUAL_ORIGIN
        self._time_scale = _scale(time_scale)

    @property
    def time_scale(self) -> float:
        return self._time_scale

    @property
    def loop(self) -> VirtualLoop:
        """The loop whose time this clock reads."""
        return self._loop

    def now(self) -> float:
        return self._wall_offset + self._loop.time()

    def monotonic(self) -> float:
        return self._loop.time()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(seconds)

    def timeout(self, seconds: float | None) -> asyncio.Timeout:
        return asyncio.timeout(seconds)

    def call_at(
        self, when: float, callback: Callable[..., object], *args: Any
    ) -> asyncio.TimerHandle:
        return self._loop.call_at(when, callback, *args)

    def __repr__(self) -> str:
        return f"VirtualClock(now={self.now():.6f}, time_scale={self._time_scale:g})"


def current_clock() -> Clock:
    """The running loop's clock: its :class:`VirtualClock` on a virtual loop, else the real one."""
    try:
        loop = asyncio.get_running_loop()
    except RuntimeError:
        return REAL_CLOCK
    return loop.clock if isinstance(loop, VirtualLoop) else REAL_CLOCK


def emulator_clock(clock: Clock | None, time_scale: float | None = None) -> Clock | None:
    """The clock an emulator made with ``clock=`` or ``time_scale=`` runs on.

    ``time_scale`` is shorthand for ``RealClock(time_scale)``; None (no clock, no scale, or
    a scale of 1) leaves the clock to be resolved when used: the running loop's, so the same
    emulator runs on real or virtual time. Raises UsageError for a bad scale, or for both a
    clock and a scale that is not the clock's.
    """
    if clock is not None:
        if time_scale is not None and time_scale != clock.time_scale:
            raise UsageError(
                f"an emulator takes a clock or a time scale, not both ({clock!r}, "
                f"time_scale={time_scale:g}): give the clock its scale"
            )
        return clock
    if time_scale is None:
        return None
    scale = _scale(time_scale)
    return None if scale == 1.0 else RealClock(scale)


def check_loop_clock(clock: Clock, what: str) -> None:
    """Refuse (UsageError) a :class:`RealClock` given to ``what`` on a virtual loop: it would
    read the wall clock, which the loop's time does not follow (the loop's clock, or none,
    is what belongs there)."""
    if isinstance(clock, RealClock) and isinstance(current_clock(), VirtualClock):
        raise UsageError(
            f"{what} was given {clock!r}, but the running loop's time is virtual: give it the "
            "loop's clock (clock=current_clock()) or none, and no time scale"
        )


class _VirtualSelector(selectors.BaseSelector):
    """The loop's selector, wrapped: its ``select`` is where time jumps (see VirtualLoop)."""

    def __init__(self) -> None:
        self._inner = selectors.DefaultSelector()
        self.loop: VirtualLoop | None = None  # set once the loop's own wake-up socket is in
        self.registered = 0  # file descriptors registered (kept here: asked every turn)

    def register(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        loop = self.loop
        if loop is not None and not loop.allow_real_io:
            fd = fileobj if isinstance(fileobj, int) else fileobj.fileno()
            raise UsageError(
                f"a virtual-time loop takes no real I/O (file descriptor {fd}): its time would "
                "jump past the moment a real peer answers. Join machines with mem:// links, or "
                "make the loop with allow_real_io=True to wait in real time while real I/O is open"
            )
        key = self._inner.register(fileobj, events, data)
        self.registered += 1
        return key

    def unregister(self, fileobj: Any) -> selectors.SelectorKey:
        key = self._inner.unregister(fileobj)
        self.registered -= 1
        return key

    def modify(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        return self._inner.modify(fileobj, events, data)

    def get_key(self, fileobj: Any) -> selectors.SelectorKey:
        return self._inner.get_key(fileobj)

    def get_map(self) -> Mapping[Any, selectors.SelectorKey]:
        return self._inner.get_map()

    def close(self) -> None:
        self._inner.close()

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        loop = self.loop
        if loop is None:
            return self._inner.select(timeout)
        if timeout == 0:
            # Callbacks are ready: no time passes. With no real I/O and no thread outside,
            # only the loop's own wake-up socket is registered, and a thread's wake-up is
            # in the ready queue already: the poll (a system call a turn) is skipped, and
            # the socket drained at the next jump.
            return self._inner.select(0) if loop._outside_pending() else []
        if loop._outside_pending():
            # Something already there (a thread's wake-up, real I/O)? Then no time passes.
            ready = self._inner.select(0)
            if ready:
                return ready
            return loop._wait_real(self._inner, timeout)
        if loop._ready:  # type: ignore[attr-defined]
            # A thread's call_soon_threadsafe lands in the ready queue before it writes to
            # the wake-up socket: no time passes (and no system call a jump).
            return []
        if timeout is None:
            raise loop._stalled()
        loop._jump(timeout)
        return []


class VirtualLoop(asyncio.SelectorEventLoop):
    """An event loop whose time jumps to the next timer when every task waits.

    ``start`` is the wall time the run begins at (a datetime, or unix seconds; now if None);
    ``allow_real_io`` takes real file descriptors and waits in real time while any is open
    (see the module docstring for the rules). ``clock`` is the loop's :class:`VirtualClock`.
    """

    def __init__(
        self,
        *,
        start: datetime | float | None = None,
        time_scale: float = 1.0,
        allow_real_io: bool = False,
    ) -> None:
        self._virtual_now = VIRTUAL_ORIGIN
        self.allow_real_io = allow_real_io
        self._executor_jobs: set[asyncio.Future[Any]] = set()
        self._shutting_down_executor = 0
        self.jumps = 0
        """How many times time jumped (for benchmarks and curious tests)."""
        selector = _VirtualSelector()
        super().__init__(selector)
        # From here on every registration is real I/O: the loop's own wake-up socket is in.
        self._own_fds = selector.registered
        self._virtual_selector = selector
        selector.loop = self
        if isinstance(start, datetime):
            wall = start.timestamp()
        elif start is None:
            wall = time.time()
        else:
            wall = float(start)
        try:
            self.clock = VirtualClock(self, wall, time_scale)
        except UsageError:
            self.close()  # its wake-up sockets are open already
            raise

    def time(self) -> float:
        return self._virtual_now

    # -- executor jobs keep time from jumping -----------------------------------------------------

    def run_in_executor(
        self,
        executor: concurrent.futures.Executor | None,
        func: Callable[[*Ts], T],
        *args: *Ts,
    ) -> asyncio.Future[T]:
        future = super().run_in_executor(executor, func, *args)
        self._executor_jobs.add(future)
        future.add_done_callback(self._executor_jobs.discard)
        return future

    async def shutdown_default_executor(self, *args: Any, **kwargs: Any) -> None:
        # The executor's shutdown is waited for in a thread of its own, outside the jobs above.
        self._shutting_down_executor += 1
        try:
            await super().shutdown_default_executor(*args, **kwargs)
        finally:
            self._shutting_down_executor -= 1

    # -- for the selector -----------------------------------------------------------------------

    def _outside_pending(self) -> bool:
        """True while something outside the loop may still bring work: real I/O or threads."""
        real_fds = self._virtual_selector.registered > self._own_fds
        return real_fds or bool(self._executor_jobs) or self._shutting_down_executor > 0

    def _next_timer(self) -> float | None:
        # _run_once dropped cancelled timers from the head just before its select(): the head
        # is the timer it worked the timeout out from (nothing else runs in between).
        scheduled: list[asyncio.TimerHandle] = self._scheduled  # type: ignore[attr-defined]
        return scheduled[0].when() if scheduled else None

    def _jump(self, timeout: float) -> None:
        """Move time to the earliest timer (the one ``timeout`` was worked out from)."""
        target = self._virtual_now + timeout
        head = self._next_timer()
        if head is not None and timeout < _MAX_SELECT_S:
            # Land exactly on the timer: now + (when - now) can miss it by a rounding error.
            target = max(head, self._virtual_now)
        self._virtual_now = max(self._virtual_now, target)
        self.jumps += 1

    def _wait_real(
        self, inner: selectors.BaseSelector, timeout: float | None
    ) -> list[tuple[selectors.SelectorKey, int]]:
        """Wait as a real loop does; time moves by the real time that passed."""
        started = time.perf_counter()
        ready = inner.select(timeout)
        if not ready and timeout is not None:
            self._jump(timeout)  # the timer's moment came: land on it
        else:
            elapsed = time.perf_counter() - started
            head = self._next_timer()
            target = self._virtual_now + elapsed
            if head is not None:
                target = min(target, head)
            self._virtual_now = max(self._virtual_now, target)
        return ready

    def _stalled(self) -> VirtualTimeStalled:
        waiting = [t for t in asyncio.all_tasks(self) if not t.done()]
        names = ", ".join(f"{t.get_name()} ({t.get_coro()!r})" for t in waiting[:5])
        more = f" and {len(waiting) - 5} more" if len(waiting) > 5 else ""
        return VirtualTimeStalled(
            "virtual time stalled: every task waits and no timer, I/O or executor job can wake "
            f"one (a deadlock, or a wait without a deadline); waiting: {names or 'none'}{more}"
        )


def run_virtual(
    main: Coroutine[Any, Any, T],
    *,
    start: datetime | float | None = None,
    time_scale: float = 1.0,
    allow_real_io: bool = False,
    debug: bool | None = None,
) -> T:
    """Run ``main`` to its end on a new :class:`VirtualLoop`, as ``asyncio.run`` does.

    ``start`` is the wall time the run begins at (``clock.now()`` in it); see the module
    docstring for the loop's rules.
    """

    def factory() -> asyncio.AbstractEventLoop:
        return VirtualLoop(start=start, time_scale=time_scale, allow_real_io=allow_real_io)

    with asyncio.Runner(debug=debug, loop_factory=factory) as runner:
        return runner.run(main)


__all__ = [
    "REAL_CLOCK",
    "VIRTUAL_ORIGIN",
    "Clock",
    "RealClock",
    "VirtualClock",
    "VirtualLoop",
    "VirtualTimeStalled",
    "check_loop_clock",
    "current_clock",
    "emulator_clock",
    "run_virtual",
]
