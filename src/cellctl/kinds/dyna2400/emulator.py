"""A Dyna 2400 CNC mill controller emulator, faithful to ``spec/dyna2400-cnc.md``.

Serve it and drive it with the mill driver, the CLI, or raw bytes::

    mill = Dyna2400Emulator(time_scale=100.0)           # automatic operator by default
    server = await serve(mill, "rfc2217://127.0.0.1:0", MILL_LINE)
    ...                                                 # host talks to server.url
    mill.set_fault("drop", "5")                         # drop the line 5 lines into a block
    assert mill.blocks_run == 2

What it models:

- The operator panel (appendix B): power on (backlash check), clear memory, LINE No / SHIFT /
  Read-Write then No, Yes, No, Yes to PROGRAM EXECUTE, READY; after a block with SETUP the
  operator jogs to the reference zero and presses NEXT. ``automatic=True`` (the default) plays
  the operator with the delays of :class:`OperatorDelays`; ``automatic=False`` leaves every
  step to :meth:`power_on`, :meth:`clear_memory`, :meth:`select`, :meth:`jog_to_reference`,
  :meth:`press_next` (the CLI maps keys to them).
- Memory of 1000 numbered lines that a transmission overwrites line by line without clearing:
  stale lines stay and run if a block leaves a gap, as users report.
- Program execute: a block runs once both ``SKIP TO 900`` and the ``900`` line have arrived;
  RTS is low while the setup is pending and while a block executes, high when READY. END
  returns the controller to manual (the automatic operator readies it again after
  ``OperatorDelays.again``, so the host can initialize it anew). Ctrl-Z ends a transmission.
- Execution with the shared DYNALAN machine model (:mod:`cellctl.kinds.dyna2400.dynalan.machine`):
  moves take their time from distance and feed rate, divided by ``time_scale``; a move outside
  the travel or a line that is not DYNALAN puts the controller in an error condition (display
  ``ERROR nnn``, RTS low until memory is cleared), because the real controller only finds out
  when it gets there. ``errors`` keeps what happened.
- Line execute (each line runs as it arrives), program load (store only; :meth:`cycle_start`,
  the controller's start input, runs it) and upload (memory back to the host, then Ctrl-Z),
  chosen on the panel with :meth:`select`.
- Readiness on RTS (the host's CTS; RFC 2217 carries it). Over links without modem lines,
  ``readiness="inband"`` (the project's fallback, **assumed**) also sends DC1 when RTS goes
  high and DC3 when it goes low, the current level when a host connects, and answers ENQ
  with the current level.
- RTS stays low at least ``min_busy_s`` (real seconds, **assumed** 0.2) once a block or a line
  is taken: the controller's own processing time, and long enough for a host to see it.
- Fault switches, :data:`FAULTS`: ``never-ready``, ``no-next``, ``drop[=N]``, ``stall``,
  ``noise=RATE[,SEED]``.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any

from cellctl.clock import Clock, emulator_clock
from cellctl.emulators.headstart import HeadStart
from cellctl.emulators.onsets import FaultOnsets
from cellctl.emulators.serve import DeviceLine, EmulatedDevice, LineNoise
from cellctl.emulators.switches import check_switch
from cellctl.errors import LinkClosed, UsageError
from cellctl.kinds.dyna2400.dynalan.machine import (
    Entry,
    MachineConfig,
    MachineState,
    Outcome,
    ProgramFault,
    checked_execute,
    run_block,
)
from cellctl.kinds.dyna2400.dynalan.model import Statement
from cellctl.kinds.dyna2400.dynalan.parser import END_OF_TRANSMISSION, decode_line, parse_line
from cellctl.kinds.dyna2400.dynalan.table import (
    BLOCK_END_LINE,
    CTRL_Z,
    DC1,
    DC3,
    ENQ,
    LINE_END,
    LOAD_MAX_LINES,
    MEMORY_LINES,
    Kind,
    Units,
)
from cellctl.tasks import cancel_and_wait

#: Lines run without motion between two yields to the event loop.
_YIELD_EVERY = 1000

FAULTS = {
    "never-ready": "the controller never shows READY: RTS stays low",
    "no-next": "the operator never presses NEXT after SETUP: RTS stays low",
    "drop": "=N: drop the connection N lines into the next block (default 5 lines)",
    "stall": "CTS stuck low: after the next block RTS never rises again",
    "noise": "=RATE[,SEED]: every byte, each way, flipped in one bit or dropped with "
    "probability RATE (e.g. 3e-4,7)",
}


class LinkMode(enum.Enum):
    """What the RS-232 link does, chosen on the panel (Read/Write menu)."""

    MANUAL = "MANUAL"
    UPLOAD = "UPLOAD"
    PROGRAM_LOAD = "DOWNLOAD"
    LINE_EXECUTE = "LINE EXECUTE"
    PROGRAM_EXECUTE = "PROGRAM EXECUTE"


@dataclass
class OperatorDelays:
    """How long the automatic operator takes, in machine seconds (divided by the time scale)."""

    power_on: float = 3.0  # backlash check
    keys: float = 2.0  # clear memory and walk the Read/Write menu
    setup: float = 20.0  # jog the axes to the reference zero and press NEXT
    # After END (the host's HALT, or an emergency stop's), walk back to the panel and select
    # the link mode again, so the host can initialize the mill anew.
    again: float = 30.0


@dataclass
class BlockRun:
    """One block or loaded program the controller ran: lines executed and how it ended."""

    lines_executed: int = 0
    machining_s: float = 0.0
    outcome: str = "running"


@dataclass
class _Rx:
    buffer: bytearray = field(default_factory=bytearray)
    saw_skip_900: bool = False
    block_lines: int = 0
    loaded: int = 0


class Dyna2400Emulator(EmulatedDevice, HeadStart):
    """The controller: panel, memory, link modes, execution, faults (see module docstring)."""

    def __init__(
        self,
        *,
        time_scale: float | None = None,
        clock: Clock | None = None,
        automatic: bool = True,
        delays: OperatorDelays | None = None,
        config: MachineConfig | None = None,
        readiness: str = "modem",
        mode: LinkMode = LinkMode.PROGRAM_EXECUTE,
        min_busy_s: float = 0.2,
    ) -> None:
        if readiness not in ("modem", "inband"):
            raise UsageError(f"readiness is 'modem' or 'inband', not {readiness!r}")
        self._clock = emulator_clock(clock, time_scale)
        self.automatic = automatic
        self.delays = delays or OperatorDelays()
        self.config = config or MachineConfig()
        self.readiness = readiness
        self.auto_mode = mode
        self.min_busy_s = min_busy_s
        self.faults: dict[str, str | None] = {}
        self.onsets = FaultOnsets()
        self.powered = False
        self.mode = LinkMode.MANUAL
        self.display = "OFF"
        self.memory: dict[int, str] = {}
        self.machine = MachineState.initial(Units.INS)
        self.reference_zero_set = False
        self.executing = False
        self.error: str | None = None
        self.errors: list[str] = []
        self.runs: list[BlockRun] = []
        self.run_hooks: list[Callable[[BlockRun], None]] = []
        """Called with each run as it starts (a cell emulator notes which part was cut)."""
        self.overruns = 0
        self.rts = False
        self._line: DeviceLine | None = None
        self._rx = _Rx()
        self._next = asyncio.Event()
        self._tasks: set[asyncio.Task[None]] = set()
        self._operator: asyncio.Task[None] | None = None
        self._execution: asyncio.Task[None] | None = None
        self._connected = asyncio.Event()
        self.failed = asyncio.Event()
        """Set when the controller enters its error condition (cleared by clear_memory)."""
        self.transmission_ended = asyncio.Event()
        """Set at each Ctrl-Z (clear it to wait for the next): a load has fully arrived."""

    # -- the operator panel ----------------------------------------------------------------------

    def power_on(self) -> None:
        """Power on: the backlash check runs, then manual mode. Memory survives (battery)."""
        self.powered = True
        self.mode = LinkMode.MANUAL
        self.display = "MANUAL"
        self._set_rts(False)

    def power_off(self) -> None:
        """Power off: everything stops, RTS drops."""
        self._cancel_execution()
        self.powered = False
        self.mode = LinkMode.MANUAL
        self.display = "OFF"
        self._set_rts(False)

    def clear_memory(self) -> None:
        """Clear the program memory and any error condition (manual mode)."""
        self._cancel_execution()
        self.memory.clear()
        self.error = None
        self.failed.clear()
        self.mode = LinkMode.MANUAL
        self.display = "MANUAL"
        self._set_rts(False)

    def select(self, mode: LinkMode) -> None:
        """Choose a link mode on the Read/Write menu (LINE No, SHIFT, Read/Write, No/Yes ...)."""
        if not self.powered:
            raise UsageError("the controller is off: power it on first")
        self._rx = _Rx()
        self.mode = mode
        if mode is LinkMode.MANUAL:
            self.display = "MANUAL"
            self._set_rts(False)
            return
        if self.executing and mode is not LinkMode.UPLOAD:
            return  # mid-block the panel shows RUN: READY comes with the block's end
        self.display = "READY" if mode is not LinkMode.UPLOAD else "UPLOAD"
        if mode is LinkMode.UPLOAD:
            self._spawn(self._upload())
        elif "never-ready" not in self.faults:
            self._set_rts(True)

    def jog_to_reference(self) -> None:
        """The operator jogs the axes to where the reference zero shall be."""
        self.machine.position = (0.0, 0.0, 0.0)
        self.reference_zero_set = True

    def press_next(self) -> None:
        """NEXT: the reference zero is set, the setup block carries on."""
        self._next.set()

    def cycle_start(self) -> None:
        """The controller's start input (wired to the cell's PLC): run the loaded program."""
        if self.executing or not self.memory or self.error:
            return
        self._start_execution(self._entries(), load_run=True)

    # -- faults --------------------------------------------------------------------------------

    def set_fault(self, name: str, arg: str | None = None) -> None:
        """Switch a fault on (names in :data:`FAULTS`)."""
        check_switch(FAULTS, name, arg)
        if name == "drop" and arg is not None and not arg.isdecimal():
            raise UsageError(f"drop takes a line count, not {arg!r}")
        if name == "noise":
            self.noise = LineNoise.parse(arg)
        self.faults[name] = arg
        self.onsets.arm(name)
        if name == "never-ready":
            self._set_rts(False)

    def clear_fault(self, name: str) -> None:
        """Switch a fault off."""
        self.faults.pop(name, None)
        if name == "noise":
            self.noise = None

    async def operator_after(self, fault: str) -> None:
        """The panel after a fault: NEXT after a setup stop nobody finished, the link mode
        selected again after a lost READY (READY comes back)."""
        if fault == "no-next":
            self.press_next()
        elif fault in ("never-ready", "stall"):
            self.select(self.auto_mode)

    async def operator_clear(self) -> None:
        """The panel after an error condition (a garbled block, a move outside the travel):
        memory cleared and the link mode selected again, READY. The reference zero and the
        setup's units, tool and feeds stay (the axes did not move): a part left in the vise
        can be cut again without a new setup over it. A block that ended without READY
        (RUN left on the display: a stall): the link mode selected again, READY."""
        if self.executing:
            return
        if self.error is not None:
            self.clear_memory()
            self.select(self.auto_mode)
        elif self.display == "RUN" and self.mode is not LinkMode.MANUAL:
            self.select(self.auto_mode)

    # -- automatic operator ---------------------------------------------------------------------

    def start(self) -> None:
        """Start the automatic operator (done by the first connection if not called)."""
        if self.automatic and self._operator is None:
            self._operator = self._spawn(self._operate())

    async def stop(self) -> None:
        """Shut down: the program executing and the automatic operator end."""
        await cancel_and_wait(self._tasks)
        self.executing = False

    async def _operate(self) -> None:
        await self._machine_sleep(self.delays.power_on)
        self.power_on()
        await self._machine_sleep(self.delays.keys)
        self.clear_memory()
        self.select(self.auto_mode)

    @property
    def blocks_run(self) -> int:
        """Blocks (and loaded programs) run to their end."""
        return sum(1 for run in self.runs if run.outcome in ("block end", "END", "HALT"))

    # -- helpers --------------------------------------------------------------------------------

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    async def _machine_sleep(self, machine_s: float) -> None:
        if machine_s > 0:
            clock = self.clock
            await clock.sleep(machine_s / clock.time_scale)

    def _set_rts(self, level: bool) -> None:
        if "never-ready" in self.faults and (level or self.rts):
            self.onsets.act("never-ready")  # READY withheld, or taken away now
        if level and ("never-ready" in self.faults or self.error):
            level = False
        if level == self.rts:
            return
        self.rts = level
        line = self._line
        if line is not None and not line.closed:
            line.set_rts(level)
            if self.readiness == "inband":
                self._spawn(self._send_quietly(bytes([DC1 if level else DC3])))

    async def _send_quietly(self, data: bytes) -> None:
        line = self._line
        if line is not None:
            with contextlib.suppress(LinkClosed):
                await line.write(data)

    def _fail(self, message: str) -> None:
        """Enter the error condition: the display says why, RTS stays low."""
        self.error = message
        self.errors.append(message)
        self.failed.set()
        self.display = f"ERROR {message}"
        self._set_rts(False)

    def _cancel_execution(self) -> None:
        if self._execution is not None and not self._execution.done():
            self._execution.cancel()
        self.executing = False

    def _entries(self) -> dict[int, Entry]:
        entries: dict[int, Entry] = {}
        for number, text in self.memory.items():
            _, statement, findings = parse_line(f"{number:03d} {text}")
            entries[number] = statement if statement is not None else findings[0][2]
        return entries

    # -- the host connection -----------------------------------------------------------------------

    async def session(self, line: DeviceLine) -> None:
        """Serve one host connection: take its lines as the selected link mode wants."""
        self._line = line
        self.start()
        line.set_rts(self.rts)
        if self.readiness == "inband":
            await line.write(bytes([DC1 if self.rts else DC3]))
        self._rx = _Rx()
        self._connected.set()
        try:
            while True:
                data = await line.read()
                if self.readiness == "inband" and ENQ in data:
                    data = data.replace(bytes([ENQ]), b"")
                    await line.write(bytes([DC1 if self.rts else DC3]))
                if not self.powered or self.mode in (LinkMode.MANUAL, LinkMode.UPLOAD):
                    continue  # nobody listens: the bytes are lost
                self._rx.buffer += data
                while True:
                    used, item = decode_line(self._rx.buffer)
                    if used == 0:
                        break
                    del self._rx.buffer[:used]
                    if item is END_OF_TRANSMISSION:
                        self._end_of_transmission()
                    elif isinstance(item, bytes):
                        await self._receive(line, item)
        finally:
            self._connected.clear()
            if self._line is line:
                self._line = None

    def _end_of_transmission(self) -> None:
        self.transmission_ended.set()
        if self.mode is LinkMode.PROGRAM_LOAD and self._rx.loaded:
            self.display = f"LOADED {self._rx.loaded}"
        self._rx = _Rx()

    async def _receive(self, line: DeviceLine, raw: bytes) -> None:
        text = raw.decode("ascii", "replace")
        if self.executing or self.error:
            # A host that ignores CTS: the controller is not listening, the line is lost.
            self.overruns += 1
            return
        if self.mode is LinkMode.LINE_EXECUTE:
            await self._line_execute(text)
            return
        number_text = text[:3]
        if not number_text.isdecimal() or (len(text) > 3 and not text[3].isspace()):
            self._fail("LINE NO")
            return
        number = int(number_text)
        body = text[3:].strip()
        if self.mode is LinkMode.PROGRAM_LOAD:
            self._rx.loaded += 1
            if self._rx.loaded > LOAD_MAX_LINES or number >= MEMORY_LINES:
                self._fail("MEMORY FULL")
                return
            self.memory[number] = body
            return
        # Program execute: store, and run once both closing lines are in.
        self.memory[number] = body
        self._rx.block_lines += 1
        drop = self.faults.get("drop", "absent")
        if drop != "absent" and self._rx.block_lines >= int(drop or 5):
            self.faults.pop("drop")
            self.onsets.act("drop")
            line.drop()
            raise LinkClosed("fault: connection dropped mid-block")
        if body == "END":
            self._end_program()
            return
        if number == BLOCK_END_LINE and not body and self._rx.saw_skip_900:
            self._rx = _Rx()
            self._start_execution(self._entries(), load_run=False)
            return
        if body.replace(" ", "") == f"SKIPTO{BLOCK_END_LINE}":
            self._rx.saw_skip_900 = True

    def _log_run(self, run: BlockRun) -> None:
        self.runs.append(run)
        for hook in list(self.run_hooks):
            hook(run)

    def _end_program(self) -> None:
        self.mode = LinkMode.MANUAL
        self.display = "MANUAL"
        self._set_rts(False)
        self._log_run(BlockRun(1, 0.0, "END"))
        if self.automatic:
            self._spawn(self._ready_again())

    async def _ready_again(self) -> None:
        """The automatic operator readies the controller again after END (appendix B's keys)."""
        await self._machine_sleep(self.delays.again)
        while self.executing:  # a block that started as END came: the operator waits it out
            await self._machine_sleep(1.0)
        # Only from where END left it: the operator does not override what happened since.
        if self.powered and self.mode is LinkMode.MANUAL:
            self.select(self.auto_mode)

    def _start_execution(self, entries: dict[int, Entry], *, load_run: bool) -> None:
        self.executing = True
        self._set_rts(False)
        self._execution = self._spawn(self._execute(entries, load_run))

    async def _execute(self, entries: dict[int, Entry], load_run: bool) -> None:
        clock = self.clock
        started = clock.monotonic()
        run = BlockRun()
        self._log_run(run)
        self.display = "RUN"
        outcome = Outcome.BLOCK_END
        # The block keeps the model's time: each move ends when the model says, counted from
        # the start, so the event loop's lateness on each sleep does not add up over a block.
        due = started
        try:
            for step in run_block(entries, self.machine, self.config):
                run.lines_executed += 1
                if step.operator:
                    await self._setup_stop()
                    due = clock.monotonic()  # the operator's time is the operator's
                seconds = sum(move.seconds for move in step.moves)
                run.machining_s += seconds
                seconds = self.skip_done(seconds)  # a cut taken up mid-way (headstart.py)
                if seconds > 0:
                    due += seconds / clock.time_scale
                    await clock.sleep(max(0.0, due - clock.monotonic()))
                elif run.lines_executed % _YIELD_EVERY == 0:
                    # Lines without motion take no machine time, but a REPEAT of them must not
                    # hold the event loop (the link and the other machines go on meanwhile).
                    await clock.sleep(0)
                if step.outcome is not None:
                    outcome = step.outcome
        except ProgramFault as fault:
            run.outcome = "error"
            self.executing = False
            self._fail(str(fault))
            return
        run.outcome = outcome.value
        # The controller's own processing time: RTS stays low at least this long.
        left = self.min_busy_s - (clock.monotonic() - started)
        if left > 0:
            await clock.sleep(left)
        self.executing = False
        if outcome is Outcome.END:
            self._end_program()
            return
        if "stall" in self.faults:
            self.onsets.act("stall")  # the block ended; READY does not come
            self.display = "RUN"
            return
        self.display = "LOADED" if load_run else "READY"
        if self.mode is not LinkMode.MANUAL:
            self._set_rts(True)

    async def _setup_stop(self) -> None:
        self.display = "setup >zcxyu"
        self.reference_zero_set = False
        self._next.clear()
        if "no-next" in self.faults:
            self.onsets.act("no-next")  # the setup stop that nobody will finish
        if self.automatic and "no-next" not in self.faults:
            await self._machine_sleep(self.delays.setup)
            self.jog_to_reference()
            self.press_next()
        await self._next.wait()
        if not self.reference_zero_set:
            self.jog_to_reference()
        self.display = "RUN"

    async def _line_execute(self, text: str) -> None:
        number, statement, findings = parse_line(text)
        if statement is None:
            self._fail(findings[0][2] if findings else "LINE")
            return
        if statement.kind is Kind.END:
            self._end_program()
            return
        if statement.kind in (Kind.SKIP, Kind.REPEAT, Kind.REPEAT_END, Kind.BLANK):
            return  # nothing to do a line at a time
        self.executing = True
        self._set_rts(False)
        self._execution = self._spawn(self._run_line(statement, number or 0))

    async def _run_line(self, statement: Statement, number: int) -> None:
        clock = self.clock
        started = clock.monotonic()
        run = BlockRun()
        self._log_run(run)
        try:
            if statement.kind is Kind.SETUP:
                await self._setup_stop()
            moves = checked_execute(statement, self.machine, self.config, number)
        except ProgramFault as fault:
            run.outcome = "error"
            self.executing = False
            self._fail(str(fault))
            return
        run.lines_executed = 1
        run.machining_s = sum(move.seconds for move in moves)
        await self._machine_sleep(self.skip_done(run.machining_s))
        left = self.min_busy_s - (clock.monotonic() - started)
        if left > 0:
            await clock.sleep(left)
        run.outcome = Outcome.BLOCK_END.value
        self.executing = False
        self.display = "READY"
        self._set_rts(True)

    async def _upload(self) -> None:
        # The operator presses Yes on UPLOAD: memory goes out line by line, then Ctrl-Z.
        if self.automatic:
            await self._machine_sleep(self.delays.keys)
        await self._connected.wait()
        line = self._line
        if line is None:
            return
        data = b"".join(
            f"{number:03d} {text}".rstrip().encode("ascii") + LINE_END
            for number, text in sorted(self.memory.items())
        )
        with contextlib.suppress(LinkClosed):
            await line.write(data + bytes([CTRL_Z]))
        self.display = "MANUAL"
        self.mode = LinkMode.MANUAL
