"""The Kerf 100's driver: the mill family (:class:`cellctl.kinds.families.Mill`) over its
line protocol::

    saw = await KerfSaw.connect("rfc2217://127.0.0.1:7003", name="saw", options=SawOptions())
    await saw.setup(Path("saw_setup.cut"), force=True)      # HOME
    await saw.run(Path("bars.cut"), progress=print)         # CLEAR, CUT ..., RUN, ST until done
    print(await saw.status())                               # idle
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

from cellctl.drivers.base import LinkDriver
from cellctl.drivers.state import StateStore
from cellctl.errors import DeviceError, LinkTimeout, UsageError
from cellctl.kinds.families import RunProgress
from cellctl.link import LineSettings, Link, TrafficLog
from cellctl_saw.options import SawOptions as SawOptions
from cellctl_saw.protocol import (
    ALARMS,
    EOL,
    HOME_S,
    CutList,
    SawState,
    SawStatus,
    command,
    parse_cut_list,
    parse_reply,
    parse_status,
)


def read_cut_list(path: Path, *, setup: bool, options: SawOptions) -> CutList:
    """A cut list file, parsed and checked; UsageError with every problem before a byte goes."""
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as e:
        raise UsageError(f"{path}: cannot read: {e}") from None
    found = parse_cut_list(text, path.name, setup=setup, max_length_mm=options.max_length_mm)
    if found.problems:
        raise UsageError("; ".join(found.problems))
    return found


class KerfSaw(LinkDriver):
    """One Kerf 100 on one link (see module docstring)."""

    def __init__(
        self, link: Link, *, name: str | None, store: StateStore | None, options: SawOptions
    ) -> None:
        saved = self._attach(link, name, store)
        self.options = options
        self.initialized = bool(saved.get("homed", False))
        self.state = int(saved.get("state", SawState.NOT_HOMED))
        self._lock = asyncio.Lock()

    @classmethod
    async def connect(
        cls,
        url: str,
        *,
        name: str | None = None,
        settings: LineSettings | None = None,
        store: StateStore | None = None,
        options: SawOptions | None = None,
        trace: TrafficLog | None = None,
    ) -> KerfSaw:
        """Open ``url`` and return the driver (the machine's owner locks taken)."""
        chosen = options or SawOptions()
        return await cls._connect_owned(
            url,
            settings or LineSettings.parse("9600,8N1"),
            name=name,
            store=store,
            trace=trace,
            build=lambda link: cls(link, name=name, store=store, options=chosen),
        )

    def _set(self, state: int, homed: bool | None = None) -> None:
        self.state = state
        if homed is not None:
            self.initialized = homed
        self._persist({"state": self.state, "homed": self.initialized})

    async def _ask(self, line: bytes, timeout: float | None = None) -> bytes:
        async with self._lock:
            self.link.reset_input()  # a late reply of a timed-out command is not this one's
            await self.link.write(line)
            try:
                wait = timeout or self.options.reply_timeout
                return await self.link.read_until(EOL, timeout=wait)
            except LinkTimeout as e:
                what = line.decode().strip()
                raise LinkTimeout(f"{self.name}: no answer to {what}: {e}") from None

    async def ask(self, *words: object, timeout: float | None = None) -> str:
        """Send one command; its reply (DeviceError for a refusal)."""
        return parse_reply(await self._ask(command(*words), timeout))

    # -- the mill family -------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self.state == SawState.CUTTING

    @property
    def state_text(self) -> str:
        return SawState.words(self.state)

    @property
    def manual(self) -> bool:
        return not self.initialized and self.state != SawState.CUTTING

    @property
    def ready_wait(self) -> float:
        return self.options.ready_wait

    @property
    def setup_timeout(self) -> float:
        return self.options.setup_timeout

    def host_status(self) -> SawStatus:
        """The status from the host's state, no byte sent."""
        return SawStatus(self.state)

    async def status(self) -> SawStatus:
        """``ST``: the state, cuts done and loaded, and the alarm."""
        found = parse_status(await self._ask(command("ST")))
        homed = self.initialized and found.state != SawState.NOT_HOMED
        self._set(found.state, homed)
        return found

    async def home(self) -> str:
        """``HOME``: the carriage to its home switch (what a setup does)."""
        reply = await self.ask("HOME", timeout=self.options.home_timeout + HOME_S)
        self._set(SawState.IDLE, True)
        return reply

    async def setup(self, program: Path, *, force: bool) -> None:
        """Run the setup cut list (``HOME``); after an alarm, ``RESET`` first when forced."""
        read_cut_list(program, setup=True, options=self.options)
        if force:
            found = await self.status()
            if found.state == SawState.ALARM:
                await self.ask("RESET")
            elif found.state == SawState.CUTTING:
                await self.ask("STOP")
        await self.home()

    async def run(
        self, program: Path, *, progress: Callable[[RunProgress], None] | None = None
    ) -> None:
        """Load ``program``'s cuts, run them, and wait until the last one ends."""
        cuts = read_cut_list(program, setup=False, options=self.options)
        await self.cut(cuts, progress=progress)

    async def cut(
        self, cuts: CutList, *, progress: Callable[[RunProgress], None] | None = None
    ) -> None:
        """Load and run a checked cut list, waiting for its end (DeviceError on an alarm)."""
        total = len(cuts.cuts)

        def report(done: int, phase: str) -> None:
            if progress is not None:
                progress(RunProgress(done, total, done, total, done, total, phase))

        report(0, "sending")
        await self.ask("CLEAR")
        for c in cuts.cuts:
            await self.ask("CUT", float(c.length_mm), float(c.feed_mm_min))
        await self.ask("RUN")
        self._set(SawState.CUTTING)
        allowed = cuts.seconds * self.options.cut_margin + self.options.cut_extra
        clock = self.clock  # the cell's clock: real, or virtual in a plan (docs/clock.md)
        deadline = clock.monotonic() + allowed
        done = -1
        while True:
            found = await self.status()
            if found.done != done:
                done = found.done
                report(done, "machining")
            if found.state == SawState.ALARM:
                raise DeviceError(5, "ALARM", detail=ALARMS.get(found.alarm, str(found.alarm)))
            if found.state != SawState.CUTTING:
                break
            if clock.monotonic() > deadline:
                raise DeviceError(
                    2, "BUSY", detail=f"still cutting {self.options.cut_extra:g} s past its time"
                )
            await clock.sleep(self.options.poll)
        report(total, "done")

    async def end(self) -> str:
        """``STOP``: the blade stops; the saw is left to its operator."""
        reply = await self.ask("STOP")
        self._set(SawState.IDLE if self.initialized else SawState.NOT_HOMED)
        return reply
