"""cellctl.clock: the real clock, and the virtual-time loop's rules (docs/clock.md)."""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from datetime import UTC, datetime

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.clock import (
    REAL_CLOCK,
    VIRTUAL_ORIGIN,
    Clock,
    RealClock,
    VirtualClock,
    VirtualLoop,
    VirtualTimeStalled,
    current_clock,
    run_virtual,
)
from cellctl.errors import UsageError

SHIFT_START = datetime(2026, 11, 27, 6, 0, tzinfo=UTC)


def test_an_hour_of_sleep_is_an_hour_of_virtual_time_from_the_given_start() -> None:
    async def main() -> tuple[float, float, datetime]:
        clock = current_clock()
        started, wall = clock.monotonic(), clock.now()
        await asyncio.sleep(3600)
        await clock.sleep(1800)
        return (
            clock.monotonic() - started,
            clock.now() - wall,
            datetime.fromtimestamp(clock.now(), UTC),
        )

    elapsed, wall_elapsed, at = run_virtual(main(), start=SHIFT_START)
    assert elapsed == 5400.0
    assert wall_elapsed == pytest.approx(5400.0, abs=1e-6)
    assert at == datetime(2026, 11, 27, 7, 30, tzinfo=UTC)


def test_timeouts_fire_on_virtual_time_at_their_deadline() -> None:
    async def main() -> list[tuple[str, float]]:
        loop = asyncio.get_running_loop()
        clock = current_clock()
        seen: list[tuple[str, float]] = []
        start = loop.time()
        with pytest.raises(TimeoutError):
            async with asyncio.timeout(30):
                await asyncio.Event().wait()
        seen.append(("wait_for", loop.time() - start))
        with pytest.raises(TimeoutError):
            async with clock.timeout(12.5):
                await asyncio.sleep(1000)
        seen.append(("timeout", loop.time() - start))
        done = loop.create_future()
        clock.call_at(loop.time() + 7, done.set_result, "call_at")
        seen.append((await done, loop.time() - start))
        return seen

    assert run_virtual(main()) == [("wait_for", 30.0), ("timeout", 42.5), ("call_at", 49.5)]


def test_tasks_wake_in_the_order_of_their_times() -> None:
    async def sleeper(name: str, seconds: float, woke: list[tuple[str, float]]) -> None:
        await asyncio.sleep(seconds)
        woke.append((name, asyncio.get_running_loop().time() - VIRTUAL_ORIGIN))

    async def main() -> list[tuple[str, float]]:
        woke: list[tuple[str, float]] = []
        await asyncio.gather(
            sleeper("c", 300, woke), sleeper("a", 100, woke), sleeper("b", 200, woke)
        )
        return woke

    assert run_virtual(main()) == [("a", 100.0), ("b", 200.0), ("c", 300.0)]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(min_value=0, max_value=7 * 24 * 3600), min_size=1, max_size=30))
def test_every_timer_fires_at_its_time_in_order(delays: list[float]) -> None:
    async def main() -> list[tuple[float, float]]:
        loop = asyncio.get_running_loop()
        fired: list[tuple[float, float]] = []
        base = loop.time()
        done = loop.create_future()
        left = [len(delays)]

        def fire(when: float) -> None:
            fired.append((when, loop.time()))
            left[0] -= 1
            if not left[0]:
                done.set_result(None)

        for delay in delays:
            loop.call_at(base + delay, fire, base + delay)
        await done
        return fired

    fired = run_virtual(main())
    whens = [when for when, _ in fired]
    assert whens == sorted(whens)
    # Each fires at its own time, give or take rounding: asyncio runs every timer due within
    # its clock's resolution in one pass, so a timer a nanosecond after another fires with it.
    resolution = time.get_clock_info("monotonic").resolution
    assert all(when - resolution <= at <= when + 1e-6 for when, at in fired)


def test_a_deadlock_is_reported_not_waited_on_for_ever() -> None:
    async def stuck_forever() -> None:
        await asyncio.Event().wait()

    async def main() -> None:
        await asyncio.create_task(stuck_forever(), name="stuck-on-an-event")

    with pytest.raises(VirtualTimeStalled, match="stuck-on-an-event"):
        run_virtual(main())


def test_real_io_is_refused_before_time_can_jump_past_it() -> None:
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]

    async def connect() -> None:
        await asyncio.open_connection("127.0.0.1", port)

    async def add_reader() -> None:
        a, b = socket.socketpair()
        with a, b:
            asyncio.get_running_loop().add_reader(a.fileno(), lambda: None)

    try:
        with pytest.raises(UsageError, match="takes no real I/O"):
            run_virtual(connect())
        with pytest.raises(UsageError, match="takes no real I/O"):
            run_virtual(add_reader())
    finally:
        listener.close()


def test_with_real_io_allowed_time_waits_for_it_then_jumps_again() -> None:
    """A real reply that comes after 50 ms of real time must come before a 1 h timer."""

    async def main() -> tuple[float, float, bytes]:
        loop = asyncio.get_running_loop()
        a, b = socket.socketpair()
        a.setblocking(False)
        got: asyncio.Future[bytes] = loop.create_future()
        loop.add_reader(a.fileno(), lambda: got.done() or got.set_result(a.recv(100)))
        timer = threading.Timer(0.05, b.send, (b"reply",))
        start = loop.time()
        hour = asyncio.ensure_future(asyncio.sleep(3600))
        timer.start()
        try:
            data = await got
            replied = loop.time() - start
        finally:
            loop.remove_reader(a.fileno())
            timer.join()
            a.close()
            b.close()
        await hour  # nothing real left: the hour jumps
        return replied, loop.time() - start, data

    replied, total, data = run_virtual(main(), allow_real_io=True)
    assert data == b"reply"
    assert replied < 3600.0  # time did not jump while the socket was open
    assert total == 3600.0


def test_an_executor_job_holds_time_until_it_is_done() -> None:
    release = threading.Event()

    def job() -> str:
        release.wait(5)
        return "done"

    async def main() -> list[str]:
        order: list[str] = []

        async def in_thread() -> None:
            order.append(await asyncio.to_thread(job))

        async def long_wait() -> None:
            await asyncio.sleep(3600)
            order.append("hour")

        threading.Timer(0.05, release.set).start()
        await asyncio.gather(long_wait(), in_thread())
        return order

    assert run_virtual(main()) == ["done", "hour"]


def test_current_clock_is_the_loops() -> None:
    assert current_clock() is REAL_CLOCK

    async def virtual() -> Clock:
        return current_clock()

    async def real() -> tuple[Clock, float, float, float]:
        loop = asyncio.get_running_loop()
        before = loop.time()
        reading = current_clock().monotonic()
        return current_clock(), before, reading, loop.time()

    clock = run_virtual(virtual(), time_scale=3.0)
    assert isinstance(clock, VirtualClock) and isinstance(clock.loop, VirtualLoop)
    assert clock.time_scale == 3.0
    found, before, reading, after = asyncio.run(real())
    assert found is REAL_CLOCK and isinstance(found, Clock)
    assert before <= reading <= after  # the real clock reads the standard loop's time


@pytest.mark.parametrize("scale", [0.0, -1.0, float("nan"), float("inf")])
def test_a_time_scale_must_be_a_positive_number(scale: float) -> None:
    with pytest.raises(UsageError, match="time scale"):
        RealClock(scale)
    with pytest.raises(UsageError, match="time scale"):
        VirtualLoop(time_scale=scale)
    assert RealClock(100.0).time_scale == 100.0
