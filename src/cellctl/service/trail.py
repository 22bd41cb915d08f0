"""The dispatcher's side of the audit trail (:mod:`cellctl.service.audit`): entries written
from worker threads, so that the loop serving the cell never waits for the disk::

    trail = CallTrail(Path("cell"))
    started = trail.begin("token:ann", "mill.download", params)   # written now, "running"
    ...                                                           # the call runs meanwhile
    await trail.end(started, "ok")                                # the same entry, ended
    await trail.record("token:vera", "cell.estop", {}, "vera is a viewer: ...", collapse=True)

An acting call's entry is begun beside the call, not before it: a commit waits for the disk
(``synchronous=FULL``) and, behind another process's write, up to the journal's busy timeout;
an emergency stop must not wait for that. Its time is taken as the call begins, and the
entry is normally on disk within a commit's time of it: only a crash in that instant loses
it, long before a call of any length is under way.
A directory that is no cell (no journal, no cell.toml) gets no trail.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cellctl.clock import current_clock
from cellctl.service.audit import AuditEntry, AuditLog, keeps_trail

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Started:
    """An acting call's entry, begun (:meth:`CallTrail.begin`); None ``writing``: no trail."""

    entry: AuditEntry
    writing: asyncio.Future[AuditEntry] | None


class CallTrail:
    """The audit trail of the cell in ``directory``, for one dispatcher (see module
    docstring). One :class:`AuditLog`, opened at the first entry and shared by the threads."""

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)
        self._log: AuditLog | None = None
        self._lock = threading.Lock()  # one opening of the log, from worker threads

    def begin(self, who: str, method: str, params: Any) -> Started:
        """An acting call begins: its entry, at this time, ``running``, is written in a
        worker thread from now on (:meth:`end` waits for it). Not awaited: see the module
        docstring."""
        at = current_clock().now()
        entry = AuditEntry.running(who, method, params, at)
        if not keeps_trail(self.directory):
            return Started(entry, None)
        writing = asyncio.ensure_future(asyncio.to_thread(self._begin, who, method, params, at))
        return Started(entry, writing)

    async def end(self, started: Started, result: str) -> None:
        """The call of ``started`` ended with ``result`` (``ok``, ``cancelled``, the error's
        text): its entry says so, keeping when it began."""
        if started.writing is None:
            return
        try:
            entry = await started.writing
        except Exception as e:  # the disk, a lock held past its timeout: written whole now
            said = f"{started.entry.method} by {started.entry.who}"
            log.warning("%s: its audit entry was not written as it began: %s", said, e)
            entry = started.entry
        await asyncio.to_thread(self._end, entry, result)

    async def record(
        self, who: str, method: str, params: Any, result: str, *, collapse: bool = False
    ) -> AuditEntry | None:
        """One entry written whole (a refusal: ``collapse``, see :meth:`AuditLog.record`),
        in the cell's journal: made for it if the cell has never run but has a cell.toml.
        The entry as written (``repeats`` > 1: counted on an earlier one); None: no trail."""
        if not keeps_trail(self.directory):
            return None
        return await asyncio.to_thread(self._record, who, method, params, result, collapse)

    def _opened(self) -> AuditLog:
        with self._lock:
            if self._log is None:
                self._log = AuditLog(self.directory)
            return self._log

    def _begin(self, who: str, method: str, params: Any, at: float) -> AuditEntry:
        return self._opened().begin(who, method, params, at=at)

    def _end(self, entry: AuditEntry, result: str) -> None:
        self._opened().end(entry, result)

    def _record(
        self, who: str, method: str, params: Any, result: str, collapse: bool
    ) -> AuditEntry:
        return self._opened().record(who, method, params, result, collapse=collapse)

    def close(self) -> None:
        with self._lock:
            if self._log is not None:
                self._log.close()
                self._log = None
