"""``loop://``: every byte written comes back to be read (pyserial's loopback URL)."""

from __future__ import annotations

from cellctl.link.base import Link


class LoopLink(Link):
    """A loopback link, for trying a link's behaviour with no device at all."""

    async def _send(self, data: bytes) -> None:
        self._loop.call_soon(self._feed, data)

    async def _shutdown(self) -> None:
        return None
