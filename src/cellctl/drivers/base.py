"""What every driver shares: it owns one link and closes it.

Use a driver as an async context manager (``async with await Driver.connect(url) as d:``)
or call ``close()``.
"""

from __future__ import annotations

from typing import Self

from cellctl.link import Link


class LinkDriver:
    """Base of the machine drivers: ``link`` is theirs to close."""

    link: Link

    async def close(self) -> None:
        """Close the link."""
        await self.link.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
