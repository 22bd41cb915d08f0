"""What every driver shares: it owns one link, closes it, and keeps its host-side state.

Use a driver as an async context manager (``async with await Driver.connect(url) as d:``)
or call ``close()``. A driver's name keys its state in the cell directory's store.
"""

from __future__ import annotations

from typing import Any, Self

from cellctl.drivers.state import StateStore, machine_key
from cellctl.link import Link


class LinkDriver:
    """Base of the machine drivers: ``link`` is theirs to close, ``name`` keys their state."""

    link: Link
    name: str

    def _attach(self, link: Link, name: str | None, store: StateStore | None) -> dict[str, Any]:
        """Take ``link``; return the state saved for this machine (``{}`` if none)."""
        self.link = link
        self.name = name or link.url
        self._store = store
        self._key = machine_key(self.name)
        return store.load(self._key) if store else {}

    def _persist(self, state: dict[str, Any]) -> None:
        """Save the host-side state (nothing to do without a store)."""
        if self._store is not None:
            self._store.save(self._key, state)

    async def close(self) -> None:
        """Close the link."""
        await self.link.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
