"""The Dyna 2400's readiness as the host sees it: the controller's RTS on CTS, or DC1/DC3.

The driver keeps one :class:`Readiness` per link and asks it for the level, or waits for a
level with a deadline; in-band, it counts DC3s so a low that came and went is not missed::

    ready = Readiness(link, inband=False)
    lows = ready.lows
    ...                                           # send a block
    await ready.wait(False, timeout, lows_before=lows)
"""

from __future__ import annotations

from cellctl.errors import LinkTimeout
from cellctl.kinds.dyna2400.dynalan.table import DC1, DC3, ENQ
from cellctl.link import Link


class Readiness:
    """The controller's RTS as the host sees it: CTS, or DC1/DC3 in the data (inband)."""

    def __init__(self, link: Link, inband: bool) -> None:
        self.link = link
        self.inband = inband
        self._level: bool | None = None
        self.lows = 0  # inband: DC3 seen so far (a low we might otherwise miss)

    def _scan(self, data: bytes) -> None:
        for byte in data:
            if byte == DC1:
                self._level = True
            elif byte == DC3:
                self._level = False
                self.lows += 1

    async def level(self, timeout: float = 2.0) -> bool:
        if not self.inband:
            return await self.link.cts()
        self._scan(self.link.reset_input())
        if self._level is None:
            await self.link.write(bytes([ENQ]))
            clock = self.link.clock
            deadline = clock.monotonic() + timeout
            while self._level is None:
                left = deadline - clock.monotonic()
                if left <= 0:
                    raise LinkTimeout(f"{self.link.url}: no DC1/DC3 readiness from the controller")
                self._scan(await self.link.read(timeout=left))
        return self._level

    async def wait(self, level: bool, timeout: float, *, lows_before: int | None = None) -> None:
        """Wait until the level is ``level`` (or, for low, a DC3 came after ``lows_before``)."""
        if not self.inband:
            await self.link.wait_cts(level, timeout=timeout)
            return
        clock = self.link.clock
        deadline = clock.monotonic() + timeout
        while True:
            current = await self.level(timeout=max(0.0, deadline - clock.monotonic()))
            if current == level or (
                not level and lows_before is not None and self.lows > lows_before
            ):
                return
            left = deadline - clock.monotonic()
            if left <= 0:
                raise LinkTimeout(
                    f"{self.link.url}: readiness did not go {'high' if level else 'low'} in time"
                )
            self._scan(await self.link.read(timeout=left))
