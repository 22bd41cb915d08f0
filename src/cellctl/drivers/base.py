"""What every driver shares: it owns one link, closes it, and keeps its host-side state.

Use a driver as an async context manager (``async with await Driver.connect(url) as d:``)
or call ``close()``. A driver's name keys its state in the cell directory's store.

One owner per machine: ``connect()`` takes the machine's owner locks before it opens the link
(see :func:`take_link_locks`), so a second opener, in another process or in this one, is
refused with MachineInUse before it opens the device or sends a byte; ``close()`` gives them
back after the link is closed.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, Self

from cellctl.clock import Clock
from cellctl.drivers.state import StateStore, machine_key
from cellctl.link import LineSettings, Link, TrafficLog, open_link
from cellctl.link.keys import link_lock_paths, needs_lookup
from cellctl.link.lock import OwnerLock, refuse_if_held


def _lock_paths(url: str, name: str | None, store: StateStore | None) -> list[tuple[Path, str]]:
    """The owner locks of a machine (path, what), in the order they are taken."""
    wanted: list[tuple[Path, str]] = []
    if store is not None and name and name != url:
        wanted.append((store.lock_path(name), name))
    if not url.startswith(("loop://", "mem://")):
        # One lock per canonical key: every spelling of the link (a symlink, localhost or
        # 127.0.0.1) takes the same files (cellctl.link.keys).
        wanted.extend((path, url) for path in link_lock_paths(url))
    return wanted


async def take_link_locks(url: str, name: str | None, store: StateStore | None) -> list[OwnerLock]:
    """The owner locks of a machine, taken now (MachineInUse if another owner holds one).

    - by name in the cell, ``<cell>/state/machine-<key>.lock``, when there is a store and a
      name of its own (an ad-hoc ``--link URL`` is named after its URL: the next lock does);
    - by URL, ``<runtime dir>/link-<key>.lock``, always but for ``loop://`` and ``mem://``
      (lines inside one process, whose own open refuses a second host): two ``--link``
      commands exclude each other, and one cannot open a link a controller opened by name.

    A host name is resolved in a worker thread (up to its deadline) while the loop goes on
    serving the cell's other machines; the locks are then taken here, so a connect
    cancelled meanwhile holds none.
    """
    if needs_lookup(url):
        wanted = await asyncio.to_thread(_lock_paths, url, name, store)
    else:
        wanted = _lock_paths(url, name, store)
    return _acquire(wanted)


def _acquire(wanted: list[tuple[Path, str]]) -> list[OwnerLock]:
    locks: list[OwnerLock] = []
    try:
        for path, what in wanted:
            locks.append(OwnerLock.acquire(path, what))
    except BaseException:
        release_locks(locks)
        raise
    return locks


def refuse_if_link_held(url: str, name: str | None, store: StateStore | None) -> None:
    """MachineInUse now if another owner holds one of the locks :func:`take_link_locks`
    would take: ``cellctl run`` asks before it serves its API or opens a link."""
    for path, what in _lock_paths(url, name, store):
        refuse_if_held(path, what)


def release_locks(locks: list[OwnerLock]) -> None:
    """Give back ``locks``, last taken first."""
    for lock in reversed(locks):
        lock.release()


class LinkDriver:
    """Base of the machine drivers: ``link`` is theirs to close, ``name`` keys their state."""

    link: Link
    name: str
    #: Owner locks taken by connect(), released by close(); none for a driver built on a link.
    _owner_locks: list[OwnerLock] = []  # noqa: RUF012 - replaced per instance, never mutated
    _clock: Clock | None = None

    @property
    def clock(self) -> Clock:
        """What the driver reads the time from: the clock it was given, else its link's."""
        return self._clock or self.link.clock

    @classmethod
    async def _connect_owned(
        cls,
        url: str,
        settings: LineSettings,
        *,
        name: str | None,
        store: StateStore | None,
        trace: TrafficLog | str | Path | None,
        build: Callable[[Link], Self],
        clock: Clock | None = None,
    ) -> Self:
        """Take the machine's locks, open ``url``, and ``build`` the driver on the link; on a
        failure close what was opened and give the locks back."""
        locks = await take_link_locks(url, name, store)
        try:
            link = await open_link(url, settings, trace=trace, label=name, clock=clock)
            try:
                driver = build(link)
            except BaseException:
                await link.close()
                raise
        except BaseException:
            release_locks(locks)
            raise
        driver._owner_locks = locks
        return driver

    def _attach(
        self,
        link: Link,
        name: str | None,
        store: StateStore | None,
        clock: Clock | None = None,
    ) -> dict[str, Any]:
        """Take ``link`` (and ``clock``, if given: else the link's); return the state saved
        for this machine (``{}`` if none)."""
        self.link = link
        self._clock = clock
        self.name = name or link.url
        self._store = store
        self._key = machine_key(self.name)
        return store.load(self._key) if store else {}

    def _persist(self, state: dict[str, Any]) -> None:
        """Save the host-side state (nothing to do without a store)."""
        if self._store is not None:
            self._store.save(self._key, state)

    async def close(self) -> None:
        """Close the link, then give back the machine's owner locks."""
        try:
            await self.link.close()
        finally:
            locks, self._owner_locks = self._owner_locks, []
            release_locks(locks)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class StartOutput(Protocol):
    """A digital output wired to a machine's cycle-start input (through the cell's PLC)."""

    async def pulse(self, seconds: float) -> None: ...


class CallbackOutput:
    """A start output that calls ``fn`` (e.g. a PLC client's coil write, or an emulator's
    ``cycle_start``)."""

    def __init__(self, fn: Callable[[], object]) -> None:
        self._fn = fn

    async def pulse(self, seconds: float) -> None:
        result = self._fn()
        if asyncio.iscoroutine(result):
            await result
