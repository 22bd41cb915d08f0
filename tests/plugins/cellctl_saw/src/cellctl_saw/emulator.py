"""The Kerf 100, emulated: its line protocol (:mod:`cellctl_saw.protocol`) and a blade that
takes each cut's time on its clock, divided by its clock's ``time_scale`` (a kind builds it
with ``clock=spec.emulator_clock()``: real time scaled, or a plan's virtual time)::

    saw = KerfEmulator(time_scale=100.0)       # shorthand for clock=RealClock(100.0)
    server = await serve(saw, "rfc2217://127.0.0.1:0", LineSettings.parse("9600,8N1"))
    saw.set_fault("jam")            # the next cut jams halfway: state ALARM

Fault switches, :data:`FAULTS`. ``cycle_start()`` (a GO input) runs the loaded cuts as
``RUN`` does; ``run_hooks`` are called with each run as it starts (the emulated cell notes
which part was cut).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import dataclass

from cellctl.clock import Clock, emulator_clock
from cellctl.emulators.serve import DeviceLine, EmulatedDevice, LineNoise
from cellctl.emulators.switches import check_switch
from cellctl.errors import LinkClosed, LinkError
from cellctl_saw.protocol import (
    EOL,
    HOME_S,
    IDENT,
    MAX_FEED_MM_MIN,
    MAX_LENGTH_MM,
    Cut,
    SawState,
    SawStatus,
    command,
    status_line,
)

FAULTS = {
    "jam": "the next cut jams halfway: the blade stops, state ALARM (blade jammed) until RESET",
    "no-home": "the carriage never finds its home switch: HOME answers ERR 6",
    "noise": "=RATE[,SEED]: every byte, each way, flipped in one bit or dropped with "
    "probability RATE",
}
#: The longest command line the saw reads; a longer one is refused whole.
MAX_LINE = 80


@dataclass
class SawRun:
    """One run of the cut list: how many cuts it made."""

    cuts: int = 0


class KerfEmulator(EmulatedDevice):
    """One emulated Kerf 100 (see module docstring)."""

    def __init__(self, *, clock: Clock | None = None, time_scale: float | None = None) -> None:
        self._clock = emulator_clock(clock, time_scale)
        self.state = SawState.NOT_HOMED
        self.cuts: list[Cut] = []
        self.done = 0
        self.alarm = 0
        self.faults: set[str] = set()
        self.runs: list[SawRun] = []
        self.run_hooks: list[Callable[[SawRun], None]] = []
        self._task: asyncio.Task[None] | None = None

    # -- the panel ---------------------------------------------------------------------------------

    def set_fault(self, name: str, arg: str | None = None) -> None:
        """Switch a fault on (names in :data:`FAULTS`)."""
        check_switch(FAULTS, name, arg)  # an argument only where FAULTS says "=ARG: ..."
        if name == "noise":
            self.noise = LineNoise.parse(arg)
        else:
            self.faults.add(name)

    def clear_fault(self, name: str) -> None:
        if name == "noise":
            self.noise = None
        self.faults.discard(name)

    def start(self) -> None:
        """Power on (nothing to do: the saw waits for HOME)."""

    def cycle_start(self) -> None:
        """The GO input: run the loaded cuts, as ``RUN`` does."""
        self._run()

    # -- the machine -------------------------------------------------------------------------------

    def status(self) -> SawStatus:
        return SawStatus(self.state, self.done, len(self.cuts), self.alarm)

    def _run(self) -> str | None:
        """Start the cut list; the refusal's ``ERR`` text otherwise."""
        if self.state == SawState.ALARM:
            return "5 ALARM"
        if self.state == SawState.NOT_HOMED:
            return "1 NOT HOMED"
        if self.state == SawState.CUTTING:
            return "2 BUSY"
        if not self.cuts:
            return "4 NO CUTS"
        run = SawRun()
        self.runs.append(run)
        for hook in list(self.run_hooks):
            hook(run)
        self.state, self.done = SawState.CUTTING, 0
        self._task = asyncio.ensure_future(self._cut_all(run))
        return None

    async def _cut_all(self, run: SawRun) -> None:
        for cut in self.cuts:
            if "jam" in self.faults:
                await self.clock.sleep(cut.seconds / 2 / self.time_scale)
                self.state, self.alarm = SawState.ALARM, 1
                return
            await self.clock.sleep(cut.seconds / self.time_scale)
            self.done += 1
            run.cuts += 1
        self.state = SawState.IDLE

    def _stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
        if self.state == SawState.CUTTING:
            self.state = SawState.IDLE

    async def _home(self) -> bytes:
        if self.state == SawState.CUTTING:
            return b"ERR 2 BUSY"
        if self.state == SawState.ALARM:
            return b"ERR 5 ALARM"
        await self.clock.sleep(HOME_S / self.time_scale)
        if "no-home" in self.faults:
            self.alarm = 2
            return b"ERR 6 HOME SWITCH"
        self.state, self.alarm = SawState.IDLE, 0
        return b"OK"

    async def answer(self, line: bytes) -> bytes:
        """The reply to one command line (without its CR LF)."""
        words = line.decode("ascii", "replace").split()
        verb = words[0].upper() if words else ""
        if verb == "ID" and len(words) == 1:
            return IDENT.encode()
        if verb == "ST" and len(words) == 1:
            return status_line(self.status()).removesuffix(EOL)
        if verb == "HOME" and len(words) == 1:
            return await self._home()
        if verb == "CLEAR" and len(words) == 1:
            if self.state == SawState.CUTTING:
                return b"ERR 2 BUSY"
            self.cuts, self.done = [], 0
            return b"OK"
        if verb == "CUT" and len(words) == 3:
            return self._add_cut(words[1], words[2])
        if verb == "RUN" and len(words) == 1:
            refused = self._run()
            return b"OK" if refused is None else f"ERR {refused}".encode()
        if verb == "STOP" and len(words) == 1:
            self._stop()
            return b"OK"
        if verb == "RESET" and len(words) == 1:
            self._stop()
            self.state, self.alarm = SawState.NOT_HOMED, 0
            return b"OK"
        return b"ERR 9 UNKNOWN COMMAND"

    def _add_cut(self, length: str, feed: str) -> bytes:
        if self.state == SawState.CUTTING:
            return b"ERR 2 BUSY"
        try:
            cut = Cut(float(length), float(feed))
        except ValueError:
            return b"ERR 3 BAD CUT"
        if not (0 < cut.length_mm <= MAX_LENGTH_MM and 0 < cut.feed_mm_min <= MAX_FEED_MM_MIN):
            return b"ERR 3 BAD CUT"
        self.cuts.append(cut)
        return b"OK"

    async def session(self, line: DeviceLine) -> None:
        """Answer one host, a command a line, until it goes."""
        with contextlib.suppress(LinkClosed, LinkError):
            while True:
                raw = await line.read_until(b"\n")
                text = raw.rstrip(b"\r\n")
                too_long = len(text) > MAX_LINE
                reply = b"ERR 9 UNKNOWN COMMAND" if too_long else await self.answer(text)
                await line.write(reply + EOL)


__all__ = ["FAULTS", "KerfEmulator", "command"]
