"""An IBM 7545/7547 robot controller emulator, faithful to ``spec/ibm7545-robot.md``.

Serve it and drive it with the robot driver, the CLI, or raw bytes::

    robot = Ibm7545Emulator(time_scale=50.0)
    server = await serve(robot, "pty", ROBOT_LINE)       # cellctl.emulators.serve
    ...                                                  # host talks to server.url
    robot.set_input(3, True)                             # the cell's PLC drives an input
    robot.set_fault("corrupt-checksum", "2")             # next 2 D records carry a bad checksum
    assert [r.outcome for r in robot.runs] == ["completed"]

What it models:

- Robot state 0 (uninitialized) / 1 (initialized, auto) / 2 (executing); 5 partitions.
- Transactions exactly as the spec has them: X (Xoff, Xon, operand, Ack; return home and stop
  answer Xoff at once, Xoff again every 25 s while moving, Xon when done), R (Xoff, Xon, operand,
  D record, host Ack, ``EG``, host Ack), N (Ack per record). Every illegal request is answered
  EOT and leaves a reject status (R 02), e.g. start before initialize -> 48, select an empty
  partition -> 83, unknown operand -> 32, bad record -> 16, unknown identifier -> 96, host silent
  while a record is expected (30 s) -> 112, manipulator power off -> 128.
- Programs compiled by :mod:`cellctl.kinds.ibm7545.aml` run in the background while state
  is 2: SCARA
  inverse kinematics (link lengths assumed 400 + 250 mm), moves timed from Cartesian distance
  and speed (assumed 500 mm/s, scaled by SPEED), workspace check (data error 64, point out of
  workspace), gripper and Z on outputs 16 and 15, WRITEO, WAITI blocking until
  :meth:`set_input`, TESTI branching on an input, ZMOVE (Z only), DELAY. A loop of jumps yields
  to the event loop at each jump. Each run is logged in :attr:`runs`.
- Machine times (moves, return home, the 25 s Xoff repeat, the 30 s host timeout) are divided by
  ``time_scale``; the host timeout never below :data:`HOST_TIMEOUT_FLOOR_S` of wall time.
  Line pacing is the serving layer's (``DeviceLine``).
- Fault switches, :data:`FAULTS`: ``power-off``, ``servo-error``, ``corrupt-checksum=N``,
  ``drop``, ``silent``, ``noise=RATE[,SEED]`` (line noise, in the serving layer).

Assumptions beyond the source (all constructor arguments): ERRESET operand 24; with the
manipulator powered off the controller still answers reads (so the host can read reject 128) but
refuses X and N; a servo error refuses motion (return home, start cycle) with reject 128 and
leaves the robot uninitialized; downloads need state 1; a partition holds at most 1000
instructions (more -> reject 80).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NoReturn, TypeVar

from cellctl.clock import Clock, emulator_clock
from cellctl.emulators.onsets import FaultOnsets
from cellctl.emulators.serve import DeviceLine, LineNoise
from cellctl.emulators.switches import check_switch
from cellctl.errors import ProtocolError, UsageError
from cellctl.kinds.ibm7545.aml import PORTS, decode_program
from cellctl.kinds.ibm7545.execution import (
    Z_DOWN_OUTPUT,
    LoadedProgram,
    ProgramExecution,
    ProgramRun,
)
from cellctl.kinds.ibm7545.motion import SPEED_MM_S, STOP_S, ScaraArm
from cellctl.kinds.ibm7545.records import (
    ACK,
    CR,
    END_GOOD,
    END_RECORD,
    EOT,
    LF,
    N_RECORD_LENGTH,
    PARTITIONS,
    POWER_FAILURE_FLAG,
    SERVO_ERROR_FLAG,
    UNDEFINED_RECORD,
    XOFF,
    XON,
    DiDo,
    ExecuteOperand,
    MachineStatus,
    ReadOperand,
    Record,
    decode_operand,
    decode_record,
    emulator_input_of,
    encode_record,
    resync,
)

__all__ = ["FAULTS", "Ibm7545Emulator", "LoadedProgram", "ProgramRun", "ScaraArm"]

T = TypeVar("T")

#: The least wall time the emulator waits for the host's next byte, whatever the time scale:
#: at x1000 the 30 s host timeout would be 30 ms, and a host process that is merely not
#: scheduled on a loaded machine would be answered as if it had gone silent.
HOST_TIMEOUT_FLOOR_S = 1.0

#: Fault switches: name -> what it does (``--fault NAME[=ARG]`` on the command line).
FAULTS: dict[str, str] = {
    "power-off": "manipulator power off: X and N requests answered EOT, reject 128; "
    "machine status power failure (64)",
    "servo-error": "servo error: status byte 128, motion refused (reject 128), cycle aborted",
    "corrupt-checksum": "=N: the next N D records sent carry a wrong checksum (default 1 record)",
    "drop": "close the connection at the next request",
    "silent": "stop answering: read every byte, send nothing",
    "noise": "=RATE[,SEED]: every byte, each way, flipped in one bit or dropped with "
    "probability RATE (e.g. 3e-4,7)",
}

# Reject codes used here (messages in cellctl.kinds.ibm7545.records.REJECT_CODES).
RECORD_FORMAT_ERROR = 16
IMPROPER_STARTUP = 48
INSUFFICIENT_MEMORY = 80
INVALID_APPLICATION = 83
INVALID_IDENTIFIER = 96
XOFF_TIME_OUT = 112
MANIPULATOR_POWER_OFF = 128


class _RequestDone(Exception):
    """The current request is finished (rejected or timed out): back to idle."""


@dataclass
class _Host:
    """One host connection: its line and the bytes received but not yet used."""

    line: DeviceLine
    buf: bytearray = field(default_factory=bytearray)


class Ibm7545Emulator(ProgramExecution):
    """The controller: state, partitions, I/O, faults. See the module docstring; a program's
    run is :class:`~cellctl.kinds.ibm7545.execution.ProgramExecution`'s."""

    def __init__(
        self,
        *,
        time_scale: float | None = None,
        clock: Clock | None = None,
        arm: ScaraArm | None = None,
        speed_mm_s: float = SPEED_MM_S,
        erreset_operand: int = ExecuteOperand.ERRESET,
        xoff_repeat_s: float = 25.0,
        host_timeout_s: float = 30.0,
        max_instructions: int = 1000,
    ) -> None:
        self._clock = emulator_clock(clock, time_scale)
        self.arm = arm or ScaraArm()
        self.speed_mm_s = speed_mm_s
        self.erreset_operand = erreset_operand
        self.xoff_repeat_s = xoff_repeat_s
        self.host_timeout_s = host_timeout_s
        self.max_instructions = max_instructions
        self.runs: list[ProgramRun] = []
        self.output_hooks: list[Callable[[int, bool], None]] = []
        """Called with (port, value) on every change of a digital output made by a program:
        how a cell emulator wires the robot's outputs to the PLC."""
        self.wait_hooks: list[Callable[[int, bool], None]] = []
        """Called with (port, value) when a program blocks in WAITI on an input that does not
        have the value yet (``cellctl emulate robot`` prints it)."""
        self.waiting_for: tuple[int, bool] | None = None
        """The input a program waits for in WAITI now, and the value it waits for."""
        self.faults: dict[str, str | None] = {}
        self.onsets = FaultOnsets()
        self.position: tuple[float, float, float, float] = self.arm.home
        self.speed_percent = 100  # SPEED(percent) of the running program; each run starts at 100
        self._corrupt_left = 0
        self._input_waiters: list[asyncio.Future[None]] = []
        self._cycle: asyncio.Task[None] | None = None
        self._abort_reason = "stopped"
        self.inputs = 0
        self.power_cycle()

    # -- outside controls ----------------------------------------------------------------------

    def power_cycle(self) -> None:
        """Cold start: state 0, partitions flushed, errors and outputs cleared."""
        self._abort("power cycle")
        self.state = 0
        self.homed = False
        self.partitions: dict[int, LoadedProgram | None] = dict.fromkeys(PARTITIONS)
        self.selected: int | None = None
        self.status_flags = 0
        self.data_error = 0
        self.reject = 0
        self.outputs = 0
        self.position = self.arm.home

    def set_input(self, port: int, value: bool | int) -> None:
        """Drive digital input ``port`` (1..16); wakes a program blocked in WAITI."""
        if port not in PORTS:
            raise UsageError(f"input port must be 1..16, not {port}")
        bit = 1 << (port - 1)
        self.inputs = self.inputs | bit if value else self.inputs & ~bit
        waiters, self._input_waiters = self._input_waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_result(None)

    def output(self, port: int) -> bool:
        """State of digital output ``port`` (1..16)."""
        return DiDo(self.inputs, self.outputs).output(port)

    def set_fault(self, name: str, arg: str | None = None) -> None:
        """Switch a fault on (names in :data:`FAULTS`)."""
        check_switch(FAULTS, name, arg)
        if name == "corrupt-checksum":
            try:
                self._corrupt_left = int(arg) if arg is not None else 1
            except ValueError:
                raise UsageError(f"corrupt-checksum needs a count, not {arg!r}") from None
            if self._corrupt_left < 0:
                raise UsageError("corrupt-checksum needs a count >= 0")
        if name == "noise":
            self.noise = LineNoise.parse(arg)
        self.faults[name] = arg
        self.onsets.arm(name)
        if name in ("power-off", "servo-error"):
            self.onsets.act(name)  # the status says so at once
        if name == "power-off":
            self._abort("manipulator power off")
            self.state = 0
            self.homed = False
        elif name == "servo-error":
            self._abort("servo error")
            self.state = 0
            self.homed = False

    def clear_fault(self, name: str) -> None:
        """Switch a fault off (no error if it was off)."""
        self.faults.pop(name, None)
        if name == "corrupt-checksum":
            self._corrupt_left = 0
        elif name == "noise":
            self.noise = None

    @property
    def machine_status(self) -> MachineStatus:
        """What R 01 answers now."""
        flags = self.status_flags | (SERVO_ERROR_FLAG if "servo-error" in self.faults else 0)
        if "power-off" in self.faults:
            flags |= POWER_FAILURE_FLAG  # the manipulator's power is gone: status says so
        return MachineStatus(flags, self.data_error)

    @property
    def running(self) -> bool:
        """True while a program executes (state 2)."""
        return self._cycle is not None and not self._cycle.done()

    @property
    def moving(self) -> bool:
        """The arm moves while a program executes."""
        return self.running

    # -- the host connection -------------------------------------------------------------------

    async def session(self, line: DeviceLine) -> None:
        """Serve one host: wait for an identifier, run its transaction, repeat."""
        host = _Host(line)
        while True:
            if not host.buf:
                host.buf += await line.read()
            byte = host.buf.pop(0)
            if "silent" in self.faults:
                self.onsets.act("silent")
                continue
            if byte in (CR, LF, ACK, XON, XOFF, 0):
                continue  # line noise and stray handshakes between transactions
            if "drop" in self.faults:
                self.faults.pop("drop")
                self.onsets.act("drop")
                line.drop()
                return
            with contextlib.suppress(_RequestDone):
                if byte == ord("X"):
                    await self._execute(host)
                elif byte == ord("R"):
                    await self._read(host)
                elif byte == ord("N"):
                    await self._download(host)
                else:
                    await self._reject(host, INVALID_IDENTIFIER)

    async def _send(self, host: _Host, data: bytes) -> None:
        if "silent" not in self.faults:
            await host.line.write(data)

    async def _reject(self, host: _Host, code: int) -> NoReturn:
        """Enter reject status: send EOT, remember the code for R 02, end the request."""
        self.reject = code
        await self._send(host, bytes([EOT]))
        raise _RequestDone

    async def _expect(self, host: _Host, decode: Callable[[bytearray], tuple[T | None, int]]) -> T:
        """Wait (host timeout, scaled) for what ``decode`` recognises; reject on bad bytes."""
        clock = self.clock
        deadline = clock.monotonic() + max(
            self.host_timeout_s / clock.time_scale, HOST_TIMEOUT_FLOOR_S
        )
        while True:
            try:
                value, used = decode(host.buf)
            except ProtocolError:
                del host.buf[: resync(host.buf)]
                await self._reject(host, RECORD_FORMAT_ERROR)
            if used:
                del host.buf[:used]
            if value is not None:
                return value
            if used:
                continue
            left = deadline - clock.monotonic()
            data = await host.line.read(timeout=left) if left > 0 else b""
            if not data:
                await self._reject(host, XOFF_TIME_OUT)
            host.buf += data

    async def _expect_ack(self, host: _Host) -> None:
        def ack(buf: bytearray) -> tuple[bool | None, int]:
            if not buf:
                return None, 0
            if buf[0] != ACK:
                raise ProtocolError("expected Ack", bytes(buf[:1]))
            return True, 1

        await self._expect(host, ack)

    async def _sleep(self, machine_s: float) -> None:
        clock = self.clock
        await clock.sleep(machine_s / clock.time_scale)

    async def _busy(self, host: _Host, machine_s: float) -> None:
        """Wait ``machine_s`` of machine time, repeating Xoff every 25 s (scaled) meanwhile."""
        left = machine_s
        while left > self.xoff_repeat_s:
            await self._sleep(self.xoff_repeat_s)
            left -= self.xoff_repeat_s
            await self._send(host, bytes([XOFF]))
        await self._sleep(left)

    # -- X: execute ----------------------------------------------------------------------------

    async def _execute(self, host: _Host) -> None:
        if "power-off" in self.faults:
            await self._reject(host, MANIPULATOR_POWER_OFF)
        await self._send(host, bytes([XOFF, XON]))
        op = await self._expect(host, decode_operand)
        if op == ExecuteOperand.RETURN_HOME:
            await self._return_home(host)
        elif op == ExecuteOperand.AUTO:
            if not self.homed or self.state == 2:
                await self._reject(host, IMPROPER_STARTUP)
            self.state = 1
            await self._send(host, bytes([ACK]))
        elif op == ExecuteOperand.START_CYCLE:
            await self._start_cycle(host)
        elif op == ExecuteOperand.STOP_CYCLE:
            await self._send(host, bytes([XOFF]))
            if self.running:
                self._abort("stopped")
                await self._busy(host, STOP_S)
                if self._cycle is not None:
                    with contextlib.suppress(asyncio.CancelledError):
                        await self._cycle
            if self.state == 2:
                self.state = 1
            await self._send(host, bytes([XON]))
        elif op == self.erreset_operand:
            self.status_flags = 0
            self.data_error = 0
            self.reject = 0
            await self._send(host, bytes([ACK]))
        elif (driven := emulator_input_of(op)) is not None:
            # Not the 7545's: the emulator's stand-in for the wiring that drives its inputs.
            self.set_input(*driven)
            await self._send(host, bytes([ACK]))
        elif op in range(31, 36):
            partition = op - 30
            if self.running:
                await self._reject(host, IMPROPER_STARTUP)
            if self.partitions[partition] is None:
                await self._reject(host, INVALID_APPLICATION)
            self.selected = partition
            await self._send(host, bytes([ACK]))
        else:
            await self._reject(host, UNDEFINED_RECORD)

    async def _return_home(self, host: _Host) -> None:
        if "servo-error" in self.faults:
            await self._reject(host, MANIPULATOR_POWER_OFF)
        if self.running:
            await self._reject(host, IMPROPER_STARTUP)
        # The Xoff at once matters: the source's host discards the first byte after the operand.
        await self._send(host, bytes([XOFF]))
        await self._busy(host, self._move_time(self.position, self.arm.home))
        self.position = self.arm.home
        self.outputs &= ~(1 << (Z_DOWN_OUTPUT - 1))
        self.homed = True
        await self._send(host, bytes([XON]))

    async def _start_cycle(self, host: _Host) -> None:
        if "servo-error" in self.faults:
            await self._reject(host, MANIPULATOR_POWER_OFF)
        if self.state != 1 or self.running:
            await self._reject(host, IMPROPER_STARTUP)
        partition = self.selected
        program = self.partitions[partition] if partition is not None else None
        if partition is None or program is None:
            await self._reject(host, INVALID_APPLICATION)
        self.state = 2
        run = ProgramRun(partition, program.name, self.clock.monotonic())
        self.runs.append(run)
        self._abort_reason = "stopped"
        self._cycle = asyncio.get_running_loop().create_task(self._run(program, run))
        await self._send(host, bytes([ACK]))

    # -- R: read -------------------------------------------------------------------------------

    async def _read(self, host: _Host) -> None:
        await self._send(host, bytes([XOFF, XON]))
        op = await self._expect(host, decode_operand)
        if op == ReadOperand.MACHINE_STATUS:
            data = self.machine_status.to_bytes()
        elif op == ReadOperand.REJECT_STATUS:
            data = bytes([self.reject])
        elif op == ReadOperand.DIDO:
            data = DiDo(self.inputs, self.outputs).to_bytes()
        else:
            await self._reject(host, UNDEFINED_RECORD)
        wire = encode_record(Record("D", data))
        if self._corrupt_left > 0:
            self._corrupt_left -= 1
            if not self._corrupt_left:
                self.faults.pop("corrupt-checksum", None)
            # Add one to the last checksum digit (mod 16): a wrong checksum, still valid hex.
            digit = int(wire[-3:-2], 16)
            wire = wire[:-3] + f"{(digit + 1) % 16:X}".encode() + wire[-2:]
        await self._send(host, wire)
        await self._expect_ack(host)
        await self._send(host, encode_record(END_GOOD))
        await self._expect_ack(host)

    # -- N: download ---------------------------------------------------------------------------

    async def _download(self, host: _Host) -> None:
        if "power-off" in self.faults:
            await self._reject(host, MANIPULATOR_POWER_OFF)
        if self.state != 1:
            await self._reject(host, IMPROPER_STARTUP)
        await self._send(host, bytes([ACK]))
        host.buf[:0] = b"N"  # the rest of the N record follows: decode it whole
        header = await self._expect(host, decode_record)
        if header.ident != "N" or len(header.data) != N_RECORD_LENGTH:
            await self._reject(host, RECORD_FORMAT_ERROR)
        partition = header.data[0]
        if partition not in PARTITIONS:
            await self._reject(host, INVALID_APPLICATION)
        name = header.data[1:].decode("ascii", "replace").rstrip()
        await self._send(host, bytes([ACK]))
        body: list[Record] = []
        while True:
            rec = await self._expect(host, decode_record)
            if rec == END_RECORD:
                break
            if rec.ident != "D":
                await self._reject(host, RECORD_FORMAT_ERROR)
            if len(body) >= self.max_instructions:
                await self._reject(host, INSUFFICIENT_MEMORY)
            body.append(rec)
            await self._send(host, bytes([ACK]))
        try:
            instructions = decode_program(body)
        except ProtocolError:
            await self._reject(host, RECORD_FORMAT_ERROR)
        self.partitions[partition] = LoadedProgram(name, tuple(instructions))
        await self._send(host, bytes([ACK]))
