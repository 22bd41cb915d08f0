"""Dyna 2400 CNC mill driver.

One :class:`Dyna2400Mill` per mill; it owns its link and its host-kept state (the spec's
states 0-4, whether it was initialized, the units and feeds of its setup program), saved in
the cell directory like the robot's::

    mill = await Dyna2400Mill.connect("rfc2217://cellhost:7002", name="cnc1",
                                      store=StateStore("cell"))
    await mill.initialize("cnc1_setup.dyn")      # operator jogs to the reference zero, NEXT
    print(await mill.status())                   # state 1 "reference zero not set" ... 2
    await mill.download("base_rough.dyn")        # validated, split, streamed block by block
    await mill.end()                             # the END program: back to manual, state 0
    await mill.close()

The link (spec ``dyna2400-cnc.md``): DYNALAN lines ending CR LF, Ctrl-Z ends a transmission.
The controller says it is ready on its RTS, seen by the host as CTS: high = ready for a block;
low = the reference zero is not set yet, or a block is executing. Over a serial port or RFC
2217 the driver reads CTS from the line. Links that cannot carry modem lines (a pty, raw TCP)
are refused at connect time unless ``readiness="inband"`` is chosen: the project's fallback, in
which the controller (or a device server in front of it) also sends DC1 when RTS goes high and
DC3 when it goes low, and answers ENQ with the current one (the mill emulator does with
``readiness="inband"``).

Program execute: each block (at most 900 lines, closed by ``SKIP TO 900`` / ``900``) is sent
once CTS is high; the controller takes it (CTS goes low), runs it, and raises CTS for the next.
Every wait has a deadline: ``ready_wait`` for READY, ``accept_timeout`` (plus the wire time) for
a block to be taken, the block's estimated machining time times ``block_margin`` plus
``block_extra`` for it to finish. Programs are validated before a byte goes out.

Results: success returns a :class:`Result` with the source's message (code 0); a refusal
raises :class:`DeviceError` (the machine's state) or :class:`MillInputError` (the file),
both carrying the spec's result code and message. The host's state guards every function
(:data:`cellctl.kinds.dyna2400.states.MILL_TABLE`): read after CTS has moved it on, before any byte
of the function goes out. A forced INITIALIZE is allowed in every state: the way out of one
that is stuck.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from cellctl.clock import Clock
from cellctl.drivers.base import CallbackOutput as CallbackOutput
from cellctl.drivers.base import StartOutput
from cellctl.drivers.state import StateStore
from cellctl.errors import DeviceError, LinkTimeout, UsageError
from cellctl.files import read_text
from cellctl.kinds.dyna2400.dynalan import (
    Kind,
    MachineState,
    Program,
    ProgramRole,
    Units,
    Validation,
    ValidationContext,
    parse_program,
    validate,
)
from cellctl.kinds.dyna2400.dynalan.table import AXES, CTRL_Z, DC1, DC3, LINE_END
from cellctl.kinds.dyna2400.line import MillLine
from cellctl.kinds.dyna2400.options import MillConfig as MillConfig
from cellctl.kinds.dyna2400.options import MillState as MillState
from cellctl.kinds.dyna2400.readiness import Readiness
from cellctl.kinds.dyna2400.states import MillFunction, mill_host_state, mill_refusal
from cellctl.kinds.dyna2400.status import DOWNLOAD_RESULTS as DOWNLOAD_RESULTS
from cellctl.kinds.dyna2400.status import END_RESULTS as END_RESULTS
from cellctl.kinds.dyna2400.status import EXECUTING as EXECUTING
from cellctl.kinds.dyna2400.status import INITIALIZE_RESULTS as INITIALIZE_RESULTS
from cellctl.kinds.dyna2400.status import MILL_CONDITIONS as MILL_CONDITIONS
from cellctl.kinds.dyna2400.status import MILL_STATES as MILL_STATES
from cellctl.kinds.dyna2400.status import REFERENCE_ZERO_NOT_SET as REFERENCE_ZERO_NOT_SET
from cellctl.kinds.dyna2400.status import RUNNING as RUNNING
from cellctl.kinds.dyna2400.status import BlockTiming as BlockTiming
from cellctl.kinds.dyna2400.status import MillInputError as MillInputError
from cellctl.kinds.dyna2400.status import MillRefused as MillRefused
from cellctl.kinds.dyna2400.status import MillStatus as MillStatus
from cellctl.kinds.dyna2400.status import Progress as Progress
from cellctl.kinds.dyna2400.status import ProgressCallback as ProgressCallback
from cellctl.kinds.dyna2400.status import Result as Result
from cellctl.kinds.dyna2400.transfer import send_lines, stream_blocks
from cellctl.kinds.families import RunProgress
from cellctl.link import MILL_LINE, LineSettings, Link, TrafficLog

# MillState and MillConfig live in options.py (the registry reads them without importing
# this driver), the records (results, status, timings) in status.py, and are named here as
# before.

END_PROGRAM = "000 END"
#: How many validated programs a driver keeps (see :meth:`Dyna2400Mill.check`).
CHECKS_KEPT = 8


class Dyna2400Mill(MillLine):
    """Driver for one Dyna 2400 mill over any :class:`Link` (see module docstring); its writes
    and readiness waits are :class:`~cellctl.kinds.dyna2400.line.MillLine`'s."""

    def __init__(
        self,
        link: Link,
        *,
        name: str | None = None,
        store: StateStore | None = None,
        config: MillConfig | None = None,
        start_output: StartOutput | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.config = config or MillConfig()
        if self.config.readiness not in ("modem", "inband"):
            raise UsageError(f"readiness is 'modem' or 'inband', not {self.config.readiness!r}")
        if not link.has_modem_lines and self.config.readiness != "inband":
            raise UsageError(
                f"{link.url} cannot carry modem lines, and the Dyna 2400 says it is ready on "
                "RTS/CTS: use a serial port or rfc2217://, or choose the in-band fallback "
                '(readiness = "inband": DC1/DC3 from the controller side)'
            )
        saved = self._attach(link, name, store, clock)
        self.start_output = start_output
        self._ready = Readiness(link, self.config.readiness == "inband")
        self.state = MillState(int(saved.get("state", 0)))
        self.initialized: bool = bool(saved.get("initialized", False))
        self.units = Units(saved["units"]) if saved.get("units") else None
        self.feed: dict[str, float] = dict(saved.get("feed", {}))
        self.tool_diameter: float | None = saved.get("tool_diameter")
        self.loaded: str | None = saved.get("loaded")
        self.last_download: list[BlockTiming] = []
        self._checked: dict[tuple[str, str, str], Validation] = {}  # see check()
        self._untaken = None  # no block on its way (MillLine._send_block)

    @classmethod
    async def connect(
        cls,
        url: str,
        *,
        name: str | None = None,
        settings: LineSettings = MILL_LINE,
        store: StateStore | None = None,
        config: MillConfig | None = None,
        start_output: StartOutput | None = None,
        trace: TrafficLog | str | Path | None = None,
        clock: Clock | None = None,
    ) -> Dyna2400Mill:
        """Open ``url``; refuses (UsageError) a link without modem lines unless inband, and
        (MachineInUse, before opening anything) a mill another owner holds."""
        return await cls._connect_owned(
            url,
            settings,
            name=name,
            store=store,
            trace=trace,
            build=lambda link: cls(
                link,
                name=name,
                store=store,
                config=config,
                start_output=start_output,
                clock=clock,
            ),
            clock=clock,
        )

    # -- host-kept state --------------------------------------------------------------------------

    def _save(self) -> None:
        self._persist(
            {
                "state": self.state,
                "initialized": self.initialized,
                "units": self.units.value if self.units else None,
                "feed": self.feed,
                "tool_diameter": self.tool_diameter,
                "loaded": self.loaded,
            }
        )

    def _set_state(self, state: int) -> None:
        self.state = MillState(state)
        self._save()

    async def _guard(self, function: MillFunction, *, refresh: bool = True) -> None:
        """Refuse ``function`` if the host's state says so (after CTS moved the view on)."""
        if refresh and self.initialized and self.state in (1, 3, 4):
            await self.status()  # NEXT pressed (1 -> 2), a block or a GO done (3/4 -> 2)
        refusal = mill_refusal(function, self.state, self.initialized)
        if refusal is not None:
            raise MillRefused(
                refusal.code,
                refusal.message,
                detail=f"{self.name}: {function.value} refused by the host's state "
                f"(state {mill_host_state(self.state, self.initialized)}): {refusal.why}",
            )

    def context(self, role: ProgramRole = ProgramRole.MILLING) -> ValidationContext:
        """What the validator should assume for this mill: its setup's units and feeds."""
        initial = None
        if self.units is not None:
            initial = MachineState.initial(self.units)
            initial.feed.update({a: v for a, v in self.feed.items() if a in AXES})
            if self.tool_diameter:
                initial.tool_diameter = self.tool_diameter
        return ValidationContext(
            role=role, units=self.units, config=self.config.machine(), initial=initial
        )

    # -- programs ------------------------------------------------------------------------------

    def check(
        self, program: str | Path | Program, role: ProgramRole = ProgramRole.MILLING
    ) -> Validation:
        """Validate ``program`` (a path or a parsed program) for this mill; nothing is sent.

        A file is read every time; what the same text validated to for the same setup is
        kept (the last :data:`CHECKS_KEPT`): a cell runs its few programs again and again.
        """
        context = self.context(role)
        if isinstance(program, Program):
            return validate(program, context)
        path = Path(program)
        text = _read_text(path)
        key = (path.name, text, repr(context))
        kept = self._checked.pop(key, None)
        if kept is None:
            kept = validate(parse_program(text, name=path.name), context)
        self._checked[key] = kept  # the most recent last
        while len(self._checked) > CHECKS_KEPT:
            del self._checked[next(iter(self._checked))]
        return kept

    def _valid(
        self,
        program: str | Path | Program,
        role: ProgramRole,
        results: dict[int, str],
        missing: int,
        invalid: int,
    ) -> Validation:
        if not isinstance(program, Program) and not Path(program).exists():
            raise MillInputError(missing, results[missing], f"{program}: no such file")
        result = self.check(program, role)
        if not result.ok or result.blocks is None:
            first = result.errors[0] if result.errors else None
            detail = first.format(result.program.name) if first else "it does not split"
            more = f" (and {len(result.errors) - 1} more)" if len(result.errors) > 1 else ""
            raise MillInputError(invalid, results[invalid], detail + more, result.errors)
        return result

    # -- the library functions ---------------------------------------------------------------------

    # -- the mill family (cellctl.kinds.families.Mill) -------------------------------------------

    @property
    def running(self) -> bool:
        return self.state in RUNNING

    @property
    def state_text(self) -> str:
        return MillState.words(self.state)

    @property
    def manual(self) -> bool:
        return self.state == MillState.NOT_READY

    @property
    def ready_wait(self) -> float:
        return self.config.ready_wait

    @property
    def setup_timeout(self) -> float:
        return self.config.setup_timeout

    def host_status(self) -> MillStatus:
        """The status from the host's state, no byte sent (a busy mill: executing)."""
        busy = self.state in (MillState.INITIALIZED, *RUNNING)
        return MillStatus(self.state, False, EXECUTING if busy else None, self.initialized)

    async def setup(self, program: Path, *, force: bool) -> None:
        """INITIALIZE with the setup program (forced: the way out of any state)."""
        await self.initialize(program, force=force)

    async def run(
        self, program: Path, *, progress: Callable[[RunProgress], None] | None = None
    ) -> None:
        """Validate, split and stream ``program`` block by block until its last block ends."""
        await self.download(program, progress=progress)

    async def initialize(self, setup_program: str | Path | Program, force: bool = False) -> Result:
        """INITIALIZE: send the setup program; the operator then sets the reference zero.

        Refusals: 1 already initialized (unless ``force``, after a machine failure), 4 machine
        not ready (CTS low), 5 initialization file error (missing or not valid). State 1 after.
        """
        result = self._valid(setup_program, ProgramRole.SETUP, INITIALIZE_RESULTS, 5, 5)
        assert result.blocks is not None
        if len(result.blocks) != 1:
            raise MillInputError(5, INITIALIZE_RESULTS[5], "a setup program is one block")
        function = MillFunction.INITIALIZE_FORCE if force else MillFunction.INITIALIZE
        await self._guard(function, refresh=False)
        if not await self._wait_ready(self.config.ready_wait):
            raise DeviceError(4, INITIALIZE_RESULTS[4], detail="CTS is low: is it READY?")
        block = result.blocks[0]
        timing = BlockTiming(1, len(block.wire()) + 1, len(block.lines), self.clock.monotonic())
        await self._send_block(block, timing, None, run_s=self.config.setup_timeout)
        self._remember_setup(result)
        self.initialized = True
        self._set_state(1)
        return Result(0, INITIALIZE_RESULTS[0])

    def _remember_setup(self, result: Validation) -> None:
        units = result.program.units or Units.INS
        machine = MachineState.initial(units)
        for line in result.program.lines:
            stmt = line.statement
            if stmt is None:
                continue
            if stmt.kind is Kind.FEED:
                for axis in stmt.text["axes"]:
                    machine.feed[axis] = stmt.value("rate")
            elif stmt.kind is Kind.TD:
                machine.tool_diameter = stmt.value("diameter")
        self.units = units
        self.feed = dict(machine.feed)
        self.tool_diameter = machine.tool_diameter

    async def status(self) -> MillStatus:
        """STATUS: the state (0-4) with "reference zero not set" / "executing" and CTS.

        Reading CTS also moves the host's view on: the operator pressed NEXT (1 -> 2), a block
        or a started program finished (3/4 -> 2). Raises LinkClosed once the link closed.
        """
        # In-band readiness is the last DC1/DC3 seen: on a closed link it would still say
        # READY, and the cell would take a mill whose line is gone for well.
        self.link.check_open()
        ready = await self._cts()
        if ready and self.state in (1, 3, 4) and self.initialized:
            self._set_state(2)
        elif ready and self.state == 0:
            self._set_state(1)
        elif not ready and self.state == 1 and not self.initialized:
            self._set_state(0)
        condition = None
        if not ready and self.state == 1:
            condition = REFERENCE_ZERO_NOT_SET
        elif not ready and self.state in (2, 3, 4):
            condition = EXECUTING
        return MillStatus(self.state, ready, condition, self.initialized)

    async def _ready_for_program(self) -> None:
        await self._guard(MillFunction.DOWNLOAD)
        if not await self._cts():
            raise MillRefused(2, "Machine executing program", detail=f"{self.name}: CTS low")
        if self.state != 2:
            self._set_state(2)

    async def download(
        self,
        program: str | Path | Program,
        *,
        wait: bool = True,
        progress: ProgressCallback | None = None,
    ) -> Result:
        """DOWNLOAD: validate, split into blocks, stream them as the controller asks.

        Refusals before a byte goes out: 1 not initialized, 2 absolute zero not set / machine
        executing (CTS low), 4 file not found, 5 not a valid program (the validator's first
        error; all of them in ``problems``). Each block waits for CTS high; the last one leaves
        the mill in state 3 unless ``wait``, which waits for it to finish (state 2).
        """
        result = self._valid(program, ProgramRole.MILLING, DOWNLOAD_RESULTS, 4, 5)
        assert result.blocks is not None and result.toolpath is not None
        if any(line.kind is Kind.END for line in result.program.lines):
            raise MillInputError(
                5, DOWNLOAD_RESULTS[5], "END belongs in the end program: use end()"
            )
        await self._ready_for_program()
        await stream_blocks(
            self, result.blocks, result.toolpath.block_seconds, wait=wait, progress=progress
        )
        return Result(0, DOWNLOAD_RESULTS[0])

    async def end(self) -> Result:
        """ENDLOAD / HALT: send the END program; the controller returns to manual, state 0.

        Refusals: 2 could not open the end program; DeviceError 2 while a block executes.
        """
        text = self._end_program_text()
        program = parse_program(text, name="END")
        result = validate(program, ValidationContext(role=ProgramRole.END))
        if not result.ok:
            raise MillInputError(2, END_RESULTS[2], result.errors[0].format("END"))
        await self._wait_out_untaken()
        await self._guard(MillFunction.ENDLOAD)
        data = b"".join(line.raw.encode("ascii") + LINE_END for line in program.lines)
        lows = self._ready.lows
        await self._send(data + bytes([CTRL_Z]))
        try:
            # Back in manual mode the controller drops RTS.
            timeout = self.config.accept_timeout + self._wire_time(len(data) + 1)
            await self._ready.wait(False, timeout, lows_before=lows)
        except LinkTimeout:
            raise LinkTimeout(
                f"{self.name}: the controller did not return to manual (CTS stayed high)"
            ) from None
        self.initialized = False
        self.loaded = None
        self._set_state(0)
        return Result(0, END_RESULTS[0])

    def _end_program_text(self) -> str:
        if not self.config.end_program:
            return END_PROGRAM
        path = Path(self.config.end_program)
        if not path.is_file():
            raise MillInputError(2, END_RESULTS[2], f"{path}: no such file")
        return read_text(path, "ascii", "replace")

    async def upload(self, *, timeout: float | None = None) -> str:
        """Receive the controller's program (the operator starts UPLOAD on the panel).

        Returns the text, one line per row; raises LinkTimeout if it does not end in time.
        """
        deadline = timeout if timeout is not None else self.config.upload_timeout
        raw = await self.link.read_until(bytes([CTRL_Z]), timeout=deadline)
        text = raw[:-1].replace(bytes([DC1]), b"").replace(bytes([DC3]), b"")
        self._ready._scan(raw.replace(text, b""))
        rows = [r.strip() for r in text.decode("ascii", "replace").replace("\r", "\n").split("\n")]
        return "".join(r + "\n" for r in rows if r)

    async def line_execute(
        self, program: str | Path | Program, *, progress: ProgressCallback | None = None
    ) -> Result:
        """LINE EXECUTE: send one line at a time, each once CTS is high (any length, slow).

        SKIP TO and REPEAT cannot work a line at a time and are refused (code 5).
        """
        result = self._valid(program, ProgramRole.MILLING, DOWNLOAD_RESULTS, 4, 5)
        assert result.blocks is not None
        await self._guard(MillFunction.LINE_EXECUTE)
        lines = [line for block in result.blocks for line in block.lines[:-2]]
        flow = [
            line
            for line in lines
            if line.statement and line.statement.kind in (Kind.SKIP, Kind.REPEAT, Kind.REPEAT_END)
        ]
        if flow:
            raise MillInputError(
                5, DOWNLOAD_RESULTS[5], "line execute cannot SKIP TO or REPEAT: use download"
            )
        await send_lines(self, lines, progress)
        await self._wait_ready(self.config.block_extra)
        return Result(0, DOWNLOAD_RESULTS[0])

    async def load(self, program: str | Path | Program) -> Result:
        """PROGRAM LOAD: store a program of at most 900 lines without running it (see go())."""
        result = self._valid(program, ProgramRole.MILLING, DOWNLOAD_RESULTS, 4, 5)
        assert result.blocks is not None
        if len(result.blocks) != 1:
            raise MillInputError(
                5,
                DOWNLOAD_RESULTS[5],
                f"program load holds at most 900 lines; this is {len(result.blocks)} blocks: "
                "use download",
            )
        await self._guard(MillFunction.LOAD)
        if not await self._wait_ready(self.config.ready_wait):
            raise DeviceError(4, "Machine not ready", detail="CTS is low")
        block = result.blocks[0]
        data = block.wire() + bytes([CTRL_Z])
        started = self.clock.monotonic()
        await self._send(data)
        # No answer comes for a load: at least let the bytes cross the line before returning.
        left = started + self._wire_time(len(data)) - self.clock.monotonic()
        if left > 0:
            await self.clock.sleep(left)
        self.loaded = result.program.name
        self._save()
        return Result(0, "Load was correct")

    async def go(self) -> Result:
        """GO: start the loaded program through the start output (state 4).

        Needs a ``start_output`` (the cell wires it to the PLC) and a loaded program.
        """
        if self.start_output is None:
            raise UsageError(
                f"{self.name}: no start output configured: GO pulses a digital output wired "
                "to the controller's start input (start_output=...)"
            )
        if self.loaded is None:
            raise UsageError(f"{self.name}: nothing loaded: load a program first")
        await self._guard(MillFunction.GO)
        if not await self._wait_ready(self.config.ready_wait):
            raise DeviceError(2, "Machine executing program")
        lows = self._ready.lows
        await self.start_output.pulse(self.config.go_pulse)
        try:
            await self._ready.wait(False, self.config.accept_timeout, lows_before=lows)
        except LinkTimeout:
            raise LinkTimeout(
                f"{self.name}: the controller did not start (CTS stayed high after GO)"
            ) from None
        self._set_state(4)
        return Result(0, "Go was correct")


def _read_text(path: Path) -> str:
    try:
        return read_text(path, "ascii", "replace")
    except OSError as e:
        raise MillInputError(4, DOWNLOAD_RESULTS[4], f"{path}: {e.strerror}") from None
