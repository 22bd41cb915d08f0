"""The emulated ISO control's execution, the base of
:class:`~cellctl.kinds.iso_cnc.emulator.IsoCncEmulator`: its runs (counted, and their hooks
told, at the first block), a drip-feed's blocks started as their time comes (each leaves the
reader buffer then, and the axes stall while the next has not come), and a program run from
memory, all timed by the motion model. The emulator's reader fills ``_buffer`` and ``_lf_at``
and calls :meth:`ControlExecution._advance` as the buffer fills; CYCLE START starts the rest::

    run = self._new_run(0)                                       # counted at its first block
    self._exec_task = asyncio.ensure_future(self._execute(run))  # RMT: blocks as they come
    self._exec_task = asyncio.ensure_future(self._run_memory(run))  # MEM: the stored program
    control.stalls                                               # [Stall(start_s, seconds), ...]
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable

from cellctl.emulators.headstart import HeadStart
from cellctl.emulators.serve import EmulatedDevice
from cellctl.kinds.iso_cnc.gcode import PROGRAM_ENDS, parse_block
from cellctl.kinds.iso_cnc.motion import Machine
from cellctl.kinds.iso_cnc.panel import Activity, DripRun, EmulatorOptions, Stall
from cellctl.kinds.iso_cnc.tape import DC1


class ControlExecution(EmulatedDevice, HeadStart):
    """Runs and their blocks (see module docstring).

    The emulator sets the state below in its constructor and provides ``low_water``,
    ``_signal`` and ``_finish_read`` (its reader's flow control).
    """

    options: EmulatorOptions
    memory: dict[int, str]
    activity: Activity
    runs: list[DripRun]
    run_hooks: list[Callable[[DripRun], None]]
    _run: DripRun | None
    _machine: Machine | None
    _buffer: bytearray
    _lf_at: deque[float]
    _stopped: bool
    _started_tape: bool
    _tape_done: bool
    _free_at: float
    _read_began: float
    _block_ready: asyncio.Event

    @property
    def low_water(self) -> int:
        """Where a reader stopped by DC3 asks again with DC1; the emulator's."""
        raise NotImplementedError

    def _signal(self, code: bytes, *, rts: bool | None = None, at: float = 0.0) -> None:
        """Send DC1/DC3 to the host; the emulator's."""
        raise NotImplementedError

    def _finish_read(self) -> None:
        """End the read (DC3, back to idle); the emulator's."""
        raise NotImplementedError

    # -- runs ----------------------------------------------------------------------------------

    def _new_run(self, number: int) -> DripRun:
        """A run about to start (it counts, and its hooks hear of it, at its first block)."""
        run = DripRun(number)
        self._run = run
        return run

    def _started(self, run: DripRun) -> None:
        self.runs.append(run)
        for hook in list(self.run_hooks):
            hook(run)

    # -- execution -----------------------------------------------------------------------------

    def _advance(self, now: float) -> None:
        """Start every block whose time has come by ``now`` (loop time): a block starts at
        ``max(its LF's arrival, the previous block's end)`` and leaves the buffer then."""
        run, machine = self._run, self._machine
        while run is not None and machine is not None and not self._tape_done:
            i = self._buffer.find(b"\n")
            if i < 0:
                if self._started_tape and self._buffer.rstrip(b"\x00\r") == b"%":
                    self._tape_done = True  # the closing % (its trailer still coming)
                return
            arrived = self._lf_at[0] if self._lf_at else now
            start = max(arrived, self._free_at) if run.blocks else arrived
            if start > now:
                return
            raw = bytes(self._buffer[: i + 1])
            del self._buffer[: i + 1]
            if self._lf_at:
                self._lf_at.popleft()
            if self._stopped and len(self._buffer) <= self.low_water:
                self._stopped = False
                self._signal(DC1, rts=True)
            text = raw.replace(b"\x00", b"").replace(b"\r", b"").decode("latin-1")
            if "%" in text:
                if self._started_tape:
                    self._tape_done = True  # the closing %
                self._started_tape = True  # label skip: the rest of this line is not read
                continue
            if not self._started_tape and not text.strip():
                continue
            self._started_tape = True
            block = parse_block(run.blocks + 1, text.rstrip("\n"), [])
            if not block.words:
                continue
            if not run.blocks:
                self._started(run)
            elif arrived > self._free_at:
                # The axes stopped at the last block's end and waited for this one: a stall.
                since = (self._free_at - self._read_began) * self.time_scale
                run.stalls.append(Stall(since, (arrived - self._free_at) * self.time_scale))
            seconds = machine.step(block).seconds
            run.blocks += 1
            run.machine_s += seconds
            # A cut taken up mid-way skips what was done (headstart.py).
            self._free_at = start + self.skip_done(seconds) / self.time_scale
            if PROGRAM_ENDS & set(block.m_codes):
                self._tape_done = True

    async def _execute(self, run: DripRun) -> None:
        """Run blocks as they come (the schedule :meth:`_advance` keeps); every wait for one
        after the first is a stall."""
        clock = self.clock
        while self.activity == Activity.READING and self._run is run:
            self._advance(clock.monotonic())
            if self._tape_done:
                if self._free_at > clock.monotonic():
                    await self.clock.sleep(self._free_at - clock.monotonic())
                break
            if self._lf_at:
                wake = max(self._lf_at[0], self._free_at) if run.blocks else self._lf_at[0]
                if wake > clock.monotonic():
                    await self.clock.sleep(wake - clock.monotonic())
                continue
            self._block_ready.clear()
            await self._block_ready.wait()
        if self.activity == Activity.READING and self._run is run:
            run.done = True
            self._finish_read()

    async def _run_memory(self, run: DripRun) -> None:
        machine = Machine(self.options.motion(), trace=False)
        self._started(run)
        for n, line in enumerate(self.memory.get(run.number, "").splitlines(), 1):
            block = parse_block(n, line, [])
            seconds = machine.step(block).seconds if block.words else 0.0
            run.blocks += 1 if block.words else 0
            run.machine_s += seconds
            await self.clock.sleep(self.skip_done(seconds) / self.time_scale)
        run.done = True
        if self.activity == Activity.RUNNING:
            self.activity = Activity.IDLE

    @property
    def stalls(self) -> list[Stall]:
        """Every stall of every drip-feed run, in order."""
        return [s for r in self.runs for s in r.stalls]
