"""The Dyna 2400 driver's end of the line, the base of
:class:`~cellctl.kinds.dyna2400.driver.Dyna2400Mill`: writes paced to the line rate, the
controller's readiness (CTS, or its in-band DC1/DC3) waited on, a block sent and seen taken
(CTS low), and a block cut short as it went out waited out before END. The driver's functions
and :mod:`cellctl.kinds.dyna2400.transfer` send through these::

    await self._send(data + bytes([CTRL_Z]))           # paced (config.pace_writes)
    if not await self._wait_ready(self.config.ready_wait): ...   # CTS high in time?
    await self._send_block(block, timing, progress, run_s=60.0)  # taken, or LinkTimeout
    await self._wait_out_untaken()                     # before END
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from cellctl.drivers.base import LinkDriver
from cellctl.errors import DeviceError, LinkTimeout
from cellctl.kinds.dyna2400.dynalan import Block
from cellctl.kinds.dyna2400.dynalan.table import CTRL_Z, LINE_END
from cellctl.kinds.dyna2400.options import MillConfig
from cellctl.kinds.dyna2400.readiness import Readiness
from cellctl.kinds.dyna2400.status import BlockTiming

#: How far ahead of the wire the driver lets its writes run (seconds of line time).
_WRITE_AHEAD_S = 0.25


@dataclass
class _Untaken:
    """A block sent (or being sent) and not yet seen taken: its number, the readiness's lows
    count before it, how long taking it may take, and how long it may run; ``whole`` once its
    last line is written."""

    block: int
    lows: int
    accept_s: float
    run_s: float
    whole: bool = False


class MillLine(LinkDriver):
    """Writes and readiness waits on one mill's link (see module docstring).

    The driver sets ``config``, ``_ready`` and ``_untaken`` (None) in its constructor.
    """

    config: MillConfig
    _ready: Readiness
    # The block on its way to the controller and not yet seen taken (None: none).
    _untaken: _Untaken | None

    async def _send(
        self,
        data: bytes,
        *,
        lines: int = 0,
        progress: Callable[[int, int], None] | None = None,
        chunks: Sequence[bytes] | None = None,
    ) -> None:
        clock = self.clock
        start = clock.monotonic()
        sent = 0
        char_time = self.link.settings.char_time
        for n, piece in enumerate(chunks or [data], start=1):
            await self.link.write(piece)
            sent += len(piece)
            if progress:
                progress(n, sent)
            if self.config.pace_writes:
                ahead = start + sent * char_time - clock.monotonic() - _WRITE_AHEAD_S
                if ahead > 0:
                    await clock.sleep(ahead)

    def _wire_time(self, nbytes: int) -> float:
        return self.link.settings.wire_time(nbytes)

    async def _cts(self) -> bool:
        return await self._ready.level(self.config.ready_wait)

    async def _wait_ready(self, timeout: float) -> bool:
        try:
            await self._ready.wait(True, timeout)
        except LinkTimeout:
            return False
        return True

    async def _send_block(
        self,
        block: Block,
        timing: BlockTiming,
        progress: Callable[[int, int], None] | None,
        *,
        run_s: float,
    ) -> None:
        """Send ``block`` and wait for the controller to take it (CTS low); ``run_s`` is how
        long it may run (what :meth:`end` waits out if this is cut short once it went whole)."""
        lines = [line.render().encode("ascii") + LINE_END for line in block.lines]
        lines[-1] += bytes([CTRL_Z])
        timeout = self.config.accept_timeout + self._wire_time(len(lines[-1])) + _WRITE_AHEAD_S
        untaken = _Untaken(block.index, self._ready.lows, timeout, run_s)
        self._untaken = untaken

        def sent(n: int, nbytes: int) -> None:
            untaken.whole = n == len(lines)
            if progress is not None:
                progress(n, nbytes)

        await self._send(b"", chunks=lines, progress=sent)
        try:
            await self._ready.wait(False, timeout, lows_before=untaken.lows)
        except LinkTimeout:
            raise LinkTimeout(
                f"{self.name}: the controller did not take block {block.index} of "
                f"{block.count} (CTS stayed high {timeout:.1f} s after its last line)"
            ) from None
        self._untaken = None
        timing.taken = self.clock.monotonic()

    async def _wait_out_untaken(self) -> None:
        """Before END: wait out a block that went out whole but was not seen taken (a download
        cut short as its last lines were on the wire). The controller starts it when its
        ``900`` line arrives; an END arriving while it runs is lost, and the block's own CTS
        fall would pass for the return to manual. A block cut short before its last line
        never starts (END takes its line 000)."""
        untaken, self._untaken = self._untaken, None
        if untaken is None or not untaken.whole:
            return
        try:
            await self._ready.wait(False, untaken.accept_s, lows_before=untaken.lows)
        except LinkTimeout:
            return  # not taken after all: nothing runs
        if not await self._wait_ready(untaken.run_s):
            raise DeviceError(
                2,
                "Machine executing program",
                detail=f"{self.name}: block {untaken.block}, sent before the stop, still "
                f"runs after {untaken.run_s:.0f} s (CTS low)",
            )
