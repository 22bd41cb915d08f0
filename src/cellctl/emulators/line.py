"""The emulator's end of a host connection: :class:`DeviceLine`, paced, and :class:`LineNoise`.

A transport (:func:`cellctl.emulators.serve.serve` over a pty, TCP or RFC 2217, or
:func:`cellctl.emulators.memserve.serve_mem` on ``mem://``) makes one ``DeviceLine`` per host
connection, feeds it the host's bytes (``feed``, ``feed_closed``) and gives it a ``send`` for
the device's; the emulator's ``session`` reads and writes through it::

    request = await line.read_until(b";", timeout=1.0)   # b"" if the timeout passes
    await line.write(reply)                              # paced at the line's rate

Pacing: with ``pacing=True`` the emulator receives each host byte no sooner than it would
have crossed the wire at the line's rate, and its own bytes reach the host at that rate too,
so timings match the real line. ``pacing=False`` moves bytes as fast as they come.

Line noise (the ``noise=RATE[,SEED]`` fault every serial emulator takes): with a
:class:`LineNoise` on the device, every byte, each way, is flipped in one bit or dropped with
probability RATE (half and half), as a noisy cable would; each direction draws from its own
generator seeded from SEED, so a run can be repeated. Without a SEED the draws are the same
every run too, unless whoever switches it on gives another (an emulated cell's ``seed``,
:meth:`cellctl.emulators.cell.EmulatedCell.set_fault`: a plan's ``--seed``).
"""

from __future__ import annotations

import asyncio
import math
import random
from collections import deque
from collections.abc import Callable
from typing import Protocol

from cellctl.clock import Clock, check_loop_clock, current_clock
from cellctl.errors import LinkClosed, UsageError
from cellctl.link import LineSettings
from cellctl.link.mem import PACE_SLICE_S


class _Device(Protocol):
    """What a line needs of the device it serves: the ``noise`` fault, if set."""

    @property
    def noise(self) -> LineNoise | None: ...


# How much of this process's own scheduling delay a paced reply may take back (see write).
_CATCH_UP_S = 0.005


class LineNoise:
    """Flip one bit of, or drop, each byte with probability ``rate`` (see module docstring)."""

    def __init__(self, rate: float, seed: int | None = None) -> None:
        if not (0.0 <= rate <= 1.0) or math.isnan(rate):
            raise UsageError(f"noise rate must be between 0 and 1, not {rate}")
        self.rate = rate
        self.seed = seed
        self._rng = {d: random.Random(f"{seed}:{d}") for d in ("in", "out")}
        self.flipped = 0
        self.dropped = 0

    @classmethod
    def parse(cls, arg: str | None) -> LineNoise:
        """``"3e-4"`` or ``"3e-4,7"`` (rate, seed), as ``--fault noise=RATE[,SEED]`` gives it."""
        if arg is None or not arg.strip():
            raise UsageError("noise takes RATE[,SEED], e.g. noise=3e-4,7: its argument is missing")
        rate_text, _, seed_text = arg.partition(",")
        try:
            rate = float(rate_text)
            seed = int(seed_text) if seed_text.strip() else None
        except ValueError:
            raise UsageError(f"noise takes RATE[,SEED], e.g. noise=3e-4,7, not {arg!r}") from None
        return cls(rate, seed)

    def garble(self, data: bytes, direction: str) -> bytes:
        """``data`` as it comes out of the noisy line (``direction`` "in" or "out")."""
        rng = self._rng[direction]
        rate = self.rate
        out = bytearray()
        for byte in data:
            if rng.random() >= rate:
                out.append(byte)
            elif rng.random() < 0.5:
                self.dropped += 1
            else:
                self.flipped += 1
                out.append(byte ^ (1 << rng.randrange(8)))
        return bytes(out)


class DeviceLine:
    """The emulator's end of one host connection.

    ``read``/``read_until`` return host bytes once they have (virtually) crossed the line;
    ``write`` returns once its bytes have. ``set_rts`` drives the host's CTS where the
    transport carries modem lines. Raises :class:`LinkClosed` once the host has gone.
    """

    def __init__(
        self,
        settings: LineSettings,
        *,
        pacing: bool,
        send: Callable[[bytes], None],
        has_modem_lines: bool = False,
        on_rts: Callable[[bool], None] | None = None,
        on_drop: Callable[[], None] | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.settings = settings
        self.pacing = pacing
        self.has_modem_lines = has_modem_lines
        self.rts = False
        self._send_raw = send
        self._on_rts = on_rts
        self._on_drop = on_drop
        self._loop = asyncio.get_running_loop()
        # Made in its running loop: the clock can be resolved now.
        self.clock: Clock = clock or current_clock()
        check_loop_clock(self.clock, "an emulator's line")
        self._pending = bytearray()
        # (time the chunk's last byte is through the line, chunk length), oldest first
        self._chunks: deque[tuple[float, int]] = deque()
        self._rx_clock = 0.0
        self._tx_clock = 0.0
        self._rx_last_ready = 0.0
        self._waiter: asyncio.Future[None] | None = None
        self._deadline: float | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._closed = False
        self.bytes_in = 0
        self.bytes_out = 0
        self.device: _Device | None = None  # its ``noise`` garbles both ways

    def _noisy(self, data: bytes, direction: str) -> bytes:
        noise = self.device.noise if self.device is not None else None
        return noise.garble(data, direction) if noise is not None else data

    # -- fed by the transport ----------------------------------------------------------------

    def feed(self, data: bytes) -> None:
        """Bytes from the host arrived (called by the transport)."""
        if not data or self._closed:
            return
        data = self._noisy(data, "in")
        if not data:
            return
        now = self.clock.monotonic()
        if self.pacing:
            self._rx_clock = max(now, self._rx_clock) + len(data) * self.settings.char_time
            ready = self._rx_clock
        else:
            ready = now
        self._pending += data
        self._chunks.append((ready, len(data)))
        self.bytes_in += len(data)
        self._wake()

    def feed_closed(self) -> None:
        """The host went away (called by the transport)."""
        self._closed = True
        self._wake()

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    # -- for the emulator ----------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        """True once the host has gone (or the line was dropped)."""
        return self._closed

    def _ready_time(self, index: int) -> float:
        """When pending byte ``index`` is through the line."""
        start = 0
        for end_time, length in self._chunks:
            if index < start + length:
                return end_time - (start + length - 1 - index) * self.settings.char_time * (
                    1 if self.pacing else 0
                )
            start += length
        raise IndexError(index)

    def _take(self, n: int) -> bytes:
        if n and self._chunks:
            self._rx_last_ready = self._ready_time(n - 1)
        data = bytes(self._pending[:n])
        del self._pending[:n]
        while n and self._chunks:
            end_time, length = self._chunks[0]
            if length <= n:
                self._chunks.popleft()
                n -= length
            else:
                self._chunks[0] = (end_time, length - n)
                n = 0
        return data

    async def _wait_data(self, timeout: float | None) -> None:
        if self._closed:
            raise LinkClosed("the host closed the line")
        fut: asyncio.Future[None] = self._loop.create_future()
        self._waiter = fut
        self._deadline = None if timeout is None else self.clock.monotonic() + timeout
        if self._deadline is not None and self._timer is None:
            self._timer = self.clock.call_at(self._deadline, self._on_timer)
        try:
            await fut
        finally:
            self._waiter = None
        if self._closed:
            raise LinkClosed("the host closed the line")

    def _on_timer(self) -> None:
        # One timer per line, re-armed only when it fires: a timer per wait (cancelled as
        # soon as bytes come) would pile up in the loop's heap with a thousand lines.
        self._timer = None
        waiter, deadline = self._waiter, self._deadline
        if waiter is None or waiter.done() or deadline is None:
            return
        if self.clock.monotonic() >= deadline:
            waiter.set_result(None)
        else:
            self._timer = self.clock.call_at(deadline, self._on_timer)

    async def _until_ready(self, index: int) -> None:
        delay = self._ready_time(index) - self.clock.monotonic()
        if delay > 0:
            await self.clock.sleep(delay)

    async def read(self, max_bytes: int = 4096, timeout: float | None = None) -> bytes:
        """Host bytes that are through the line (at least one); b"" if ``timeout`` passes.

        Bytes the host wrote together are handed over together once the last of them has
        crossed the line, like a UART's receive FIFO on idle: one wake-up per write rather
        than one per character, which matters with a thousand emulated lines in one process.
        """
        deadline = None if timeout is None else self.clock.monotonic() + timeout
        while not self._pending:
            left = None if deadline is None else deadline - self.clock.monotonic()
            if left is not None and left <= 0:
                return b""
            await self._wait_data(left)
        delay = self._chunks[0][0] - self.clock.monotonic()
        if delay > 0:
            await self.clock.sleep(delay)
        now = self.clock.monotonic()
        n = 0
        for end_time, length in self._chunks:
            if end_time > now and n:
                break
            n += length
        return self._take(min(n, max_bytes))

    async def read_until(self, terminator: bytes, timeout: float | None = None) -> bytes:
        """Host bytes up to and including ``terminator``; b"" if ``timeout`` passes first."""
        deadline = None if timeout is None else self.clock.monotonic() + timeout
        while True:
            i = self._pending.find(terminator)
            if i >= 0:
                end = i + len(terminator)
                await self._until_ready(end - 1)
                return self._take(end)
            left = None if deadline is None else deadline - self.clock.monotonic()
            if left is not None and left <= 0:
                return b""
            await self._wait_data(left)

    @property
    def last_ready(self) -> float:
        """Loop time at which the last byte read had crossed the line (the bytes before it
        in one read crossed a character time apart): when a machine saw each byte."""
        return self._rx_last_ready

    def pending(self) -> bytes:
        """Host bytes received, whether or not through the line yet (not consumed)."""
        return bytes(self._pending)

    async def write(self, data: bytes) -> None:
        """Send ``data`` to the host, paced at the line's rate.

        Returns at once, as a UART does once its FIFO holds the bytes: each slice reaches the
        host when its last character has crossed the line (scheduled on the loop, no task
        switch per slice, which matters with a thousand emulated lines in one process).
        """
        if self._closed:
            raise LinkClosed("the host closed the line")
        data = self._noisy(data, "out")
        if not self.pacing:
            self.bytes_out += len(data)
            self._send_raw(data)
            return
        ct = self.settings.char_time
        step = max(1, int(PACE_SLICE_S / ct))
        now = self.clock.monotonic()
        # An answer to bytes just received starts when they ended on the line, not when this
        # process got round to it: a real controller's reply does not carry the emulator's
        # scheduling delay (up to _CATCH_UP_S of it is taken back).
        start = self._rx_last_ready if 0 <= now - self._rx_last_ready < _CATCH_UP_S else now
        self._tx_clock = max(start, self._tx_clock)
        for i in range(0, len(data), step):
            piece = data[i : i + step]
            self._tx_clock += len(piece) * ct
            self.clock.call_at(self._tx_clock, self._deliver, piece)

    def _deliver(self, piece: bytes) -> None:
        if not self._closed:
            self.bytes_out += len(piece)
            self._send_raw(piece)

    async def drain(self) -> None:
        """Wait until everything written has crossed the line."""
        delay = self._tx_clock - self.clock.monotonic()
        if delay > 0:
            await self.clock.sleep(delay)

    def set_rts(self, level: bool) -> None:
        """Drive the emulator's RTS (the host's CTS). No effect where modem lines don't travel."""
        if level == self.rts:
            return
        self.rts = level
        if self._on_rts is not None:
            self._on_rts(level)

    def drop(self) -> None:
        """Fault: cut the connection now, as a pulled cable or a crashed server would."""
        self.feed_closed()
        if self._on_drop is not None:
            self._on_drop()
