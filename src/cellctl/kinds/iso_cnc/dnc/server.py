"""The DNC server: many controls from one process, each on its own link, held exclusively.

::

    server = DncServer(load_shop(Path("SHOP")))
    await server.start()             # opens every link under its owner locks; one task each
    server.status()["mill1"].activity   # Activity.IDLE ...
    await server.send("mill1", data, drip=True, progress=print)   # by hand, between requests
    await server.line("mill1").stop()   # from another task: the transfer in flight ends cleanly
    await server.close()

Each machine's task listens for the control: a punched tape (DC2 ... DC4) is split into its
programs; the request program (:mod:`.request`) makes the control's *next read* receive the
program it names (read into memory, or drip-fed), every other program is kept as received
(:mod:`.store`), a refused request too. A transfer by hand (``dnc.send`` through the API) is
refused at once (MachineInUse) while the machine is busy, else waits until its task is between
two listens, so a transfer is never cut in two. A link that fails, or cannot be opened at the
start, is logged, shown offline naming the machine, and opened again every :data:`REOPEN_S`;
the other machines go on. A transfer stopped (``dnc.stop``, its sender's Ctrl-C with its
ticket, the server stopping) ends the way the spec ends a tape: the rest of the block in
flight, then ``%`` (the control leaves the read; a drip-feed runs the blocks it holds first);
one the control has not begun is cancelled, nothing sent. Its caller gets
:class:`TransferStopped` saying where it ended; the machine's log has it.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable

from cellctl.clock import current_clock
from cellctl.drivers.state import StateStore
from cellctl.errors import CellctlError, LinkError, UsageError
from cellctl.kinds.iso_cnc.dnc.config import ShopConfig
from cellctl.kinds.iso_cnc.dnc.line import PUNCH_S, REOPEN_S, STOP_S, TRANSFER_S, DncLine
from cellctl.kinds.iso_cnc.dnc.status import Activity, MachineStatus, offline_words, state_words
from cellctl.kinds.iso_cnc.dnc.store import ShopStore
from cellctl.link import TrafficLog

# The line's deadlines and status are read here by the API and the CLI.
__all__ = ["PUNCH_S", "STOP_S", "TRANSFER_S", "Activity", "DncLine", "DncServer"]


class DncServer:
    """The machines of one shop, each on its own task (see module docstring)."""

    def __init__(self, config: ShopConfig, *, trace: TrafficLog | None = None) -> None:
        self.config = config
        self.store = ShopStore(config.root)
        self.state = StateStore(config.root)
        self.listeners: list[Callable[[], None]] = []
        self.started = current_clock().now()
        self.lines = {
            name: DncLine(
                m,
                self.store,
                self.state,
                trace=trace,
                changed=self._changed,
                stop_command=config.command(f"stop {name}"),
            )
            for name, m in config.machines.items()
        }
        self._tasks: list[asyncio.Task[None]] = []

    def _changed(self) -> None:
        for listener in self.listeners:
            listener()

    def line(self, name: str) -> DncLine:
        found = self.lines.get(name)
        if found is None:
            known = ", ".join(sorted(self.lines))
            raise UsageError(f"unknown DNC machine {name!r} (known: {known})")
        return found

    async def start(self, *, retry: bool = True) -> None:
        """Open every machine's link, then serve. All are refused if one is owned elsewhere
        (MachineInUse); one that cannot be reached (LinkError) is shown offline, naming it,
        and its task tries again every :data:`REOPEN_S`, as for a link that fails later.
        ``retry=False`` (a one-shot command's machine): that LinkError is raised instead,
        in the same words but for the retry, which nothing would do."""
        opened: list[DncLine] = []
        try:
            for line in self.lines.values():
                line.retries = retry
                self.store.machine(line.name)
                try:
                    await line.open()
                except LinkError as e:
                    if not retry:
                        raise LinkError(offline_words(line.name, e, None)) from None
                    said = offline_words(line.name, e, REOPEN_S)
                    line._note(f"error: {said}")
                    line._set(activity=Activity.OFFLINE, error=said, failures=1)
                    continue
                opened.append(line)
        except BaseException:
            for line in opened:
                with contextlib.suppress(CellctlError):
                    await line.close()
            raise
        self._tasks = [asyncio.create_task(line.run()) for line in self.lines.values()]

    def in_flight(self) -> dict[str, str]:
        """What each machine with a transfer in flight or a request waiting does."""
        return {
            name: state_words(line.status)
            for name, line in self.lines.items()
            if (line.transfer is not None and not line.transfer.done())
            or line.pending
            or line.claimed
        }

    async def end_transfers(self, why: str) -> dict[str, str]:
        """End every transfer in flight the clean way (:meth:`DncLine.stop`: the rest of a
        block and ``%``; one not begun is cancelled) and drop waiting requests, all at once,
        each bounded by :data:`STOP_S`; what became of each, logged in its machine's log."""

        async def end(line: DncLine) -> str:
            try:
                said = await line.stop(why=why)
            except CellctlError as e:
                said = str(e)
            transfer = line.transfer
            if transfer is not None and not transfer.done():
                # All of it (or its clean end) is out, the control runs what it holds: the
                # host has nothing more to send; its sender is told so now (send() logs it).
                line.stopping = said
                transfer.cancel()
                await asyncio.wait({transfer}, timeout=STOP_S)
            return said

        names = list(self.in_flight())
        results = await asyncio.gather(*(end(self.lines[n]) for n in names))
        ended = dict(zip(names, results, strict=True))
        for name, line in self.lines.items():
            # A `dnc receive` waiting for a punch that has not begun: its call would hold the
            # server's close (calls in flight are waited for) until its own timeout.
            said = line.end_punch_wait(why)
            if said:
                ended[name] = said
        return ended

    async def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, CellctlError):
                await task
        self._tasks = []
        for line in self.lines.values():
            with contextlib.suppress(CellctlError):
                await line.close()

    def status(self) -> dict[str, MachineStatus]:
        return {name: line.status for name, line in self.lines.items()}
