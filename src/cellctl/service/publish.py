"""Pushing the cell's changes to the WebSocket sessions that subscribed: each is sent what
changed since the status it holds, bursts coalesced (the :class:`Publisher` part of
:class:`~cellctl.service.server.ApiServer`)::

    server.changed()          # the controller's state changed: subscribers are told soon
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from cellctl.clock import current_clock
from cellctl.service.status import CellStatus, difference
from cellctl.service.token import still_valid

if TYPE_CHECKING:
    from cellctl.service.access import CellAccess
    from cellctl.service.inflight import Session

log = logging.getLogger(__name__)

#: Shortest gap between two pushed updates (bursts of changes are coalesced).
PUSH_GAP = 0.01
#: Updates are looked for at least this often, signalled or not.
PUSH_TICK = 1.0


class Publisher:
    """Status updates pushed to subscribed sessions (see module docstring)."""

    _changed: asyncio.Event
    sessions: set[Session]
    directory: Path
    access: CellAccess
    push_count: int

    def changed(self) -> None:
        """The cell's state changed (called by the controller)."""
        self._changed.set()

    async def _publisher(self) -> None:
        while True:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(PUSH_TICK):
                    await self._changed.wait()
            self._changed.clear()
            subscribers = [s for s in self.sessions if s.subscribed and s.open]
            valid = {e: still_valid(self.directory, e) for e in {s.entry for s in subscribers}}
            for session in subscribers:
                if not valid[session.entry]:  # revoked: its session ends now
                    session.finish(1008)
            subscribers = [s for s in subscribers if valid[s.entry]]
            if not subscribers:
                continue
            try:
                status = self.access.status()  # built once for every subscriber
            except Exception:
                log.exception("status snapshot failed")
                continue
            self.push(status, subscribers)
            await current_clock().sleep(PUSH_GAP)

    def push(self, status: CellStatus, subscribers: list[Session]) -> None:
        """Send each subscriber what changed since the status it holds (most hold the same
        one: the difference is made and encoded once for them all)."""
        held: dict[int, tuple[CellStatus | None, list[Session]]] = {}
        for session in subscribers:
            held.setdefault(id(session.last), (session.last, []))[1].append(session)
        for last, sessions in held.values():
            update = difference(last, status)
            for session in sessions:
                session.last = status
            if update.empty():
                continue
            message = json.dumps(
                {"jsonrpc": "2.0", "method": "notify_status_update", "params": update.as_json()}
            )
            self.push_count += 1
            for session in sessions:
                session.send(message)
