"""The emulated IBM 7545's program execution, the base of
:class:`~cellctl.kinds.ibm7545.emulator.Ibm7545Emulator` (its line's transactions are the
emulator's): a partition's AML program run in the background while the robot is in state 2,
moves timed by the SCARA model and checked against its workspace, the gripper and Z mirrored
on their outputs, WAITI blocking until :meth:`set_input` gives the input its value, each run
logged as a :class:`ProgramRun`. START CYCLE starts it as a task; STOP CYCLE, a fault or a
power cycle cancels it through :meth:`ProgramExecution._abort`::

    run = ProgramRun(partition, program.name, self.clock.monotonic())
    self._cycle = asyncio.get_running_loop().create_task(self._run(program, run))
    self._abort("stopped")                  # run.outcome == "stopped" once it has ended
    robot.set_output(16, True)              # as a program's GRASP: the output hooks hear it
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass

from cellctl.emulators.serve import EmulatedDevice
from cellctl.errors import UsageError
from cellctl.kinds.ibm7545.aml import PORTS, Instruction, Op
from cellctl.kinds.ibm7545.motion import ScaraArm, fixed_seconds, move_seconds, target
from cellctl.kinds.ibm7545.records import DATA_ERROR_FLAG, DiDo

# Data error codes used here (messages in cellctl.kinds.ibm7545.records.DATA_ERRORS).
POINT_OUT_OF_WORKSPACE = 64
PROGRAMMING_ERROR = 18

Z_DOWN_OUTPUT = 15  # assumed wiring: output 15 mirrors the Z axis (1 = down)
GRIPPER_OUTPUT = 16  # assumed wiring: output 16 mirrors the gripper (1 = closed)


@dataclass(frozen=True)
class LoadedProgram:
    """A program held in a partition."""

    name: str
    instructions: tuple[Instruction, ...]


@dataclass
class ProgramRun:
    """One execution of a partition's program; ``end`` is None while it runs."""

    partition: int
    program: str
    start: float  # its clock's monotonic time
    end: float | None = None
    outcome: str = "running"  # "completed", "stopped", or the error that ended it


class ProgramExecution(EmulatedDevice):
    """A program's run on the arm and the I/O (see module docstring).

    The emulator sets the state below in its constructor (and its power cycle).
    """

    arm: ScaraArm
    speed_mm_s: float
    speed_percent: int
    position: tuple[float, float, float, float]
    state: int
    status_flags: int
    data_error: int
    inputs: int
    outputs: int
    output_hooks: list[Callable[[int, bool], None]]
    wait_hooks: list[Callable[[int, bool], None]]
    waiting_for: tuple[int, bool] | None
    _input_waiters: list[asyncio.Future[None]]
    _cycle: asyncio.Task[None] | None
    _abort_reason: str

    async def _sleep_on(self, due: list[float], machine_s: float) -> None:
        """Sleep ``machine_s`` of a program's time on its ``due`` (``[when]``, the clock's
        monotonic time): each instruction ends when the model says, counted from the run's
        start, so the event loop's lateness on each sleep does not add up over a program."""
        clock = self.clock
        due[0] += machine_s / clock.time_scale
        await clock.sleep(max(0.0, due[0] - clock.monotonic()))

    def _move_time(
        self, a: tuple[float, float, float, float], b: tuple[float, float, float, float]
    ) -> float:
        return move_seconds(a, b, self.speed_mm_s, self.speed_percent)

    def _abort(self, reason: str) -> None:
        if self._cycle is not None and not self._cycle.done():
            self._abort_reason = reason
            self._cycle.cancel()

    def set_output(self, port: int, value: bool) -> None:
        """Set digital output ``port`` (1..16) as a program's OUTPUT would: the output hooks
        hear a change (the emulated cell starting with a part clamped in a vise)."""
        if port not in PORTS:
            raise UsageError(f"output port must be 1..16, not {port}")
        bit = 1 << (port - 1)
        before = self.outputs
        self.outputs = self.outputs | bit if value else self.outputs & ~bit
        if self.outputs != before:
            for hook in list(self.output_hooks):
                hook(port, value)

    async def _wait_input(self, port: int, value: bool) -> None:
        told = False
        try:
            while DiDo(self.inputs, self.outputs).input(port) != value:
                # Any input's change wakes the wait: it still waits for this one after.
                self.waiting_for = (port, value)
                if not told:
                    for hook in list(self.wait_hooks):
                        hook(port, value)
                    told = True
                fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
                self._input_waiters.append(fut)
                await fut
        finally:
            self.waiting_for = None

    def _data_error(self, code: int) -> None:
        self.status_flags |= DATA_ERROR_FLAG
        self.data_error = code

    async def _run(self, program: LoadedProgram, run: ProgramRun) -> None:
        """Execute ``program`` until END, an error, or a stop; then state 1 (0 on power loss)."""
        pc = 0
        clock = self.clock
        due = [clock.monotonic()]
        self.speed_percent = 100
        try:
            while True:
                ins = program.instructions[pc]
                pc += 1
                if ins.op in (Op.PMOVE, Op.ZMOVE):
                    point = target(ins, self.position)
                    if not self.arm.reachable(point):
                        self._data_error(POINT_OUT_OF_WORKSPACE)
                        run.outcome = "point out of workspace"
                        break
                    await self._sleep_on(due, self._move_time(self.position, point))
                    self.position = point
                elif ins.op is Op.DELAY:
                    await self._sleep_on(due, fixed_seconds(ins))
                elif ins.op in (Op.GRASP, Op.RELEASE):
                    self.set_output(GRIPPER_OUTPUT, ins.op is Op.GRASP)
                    await self._sleep_on(due, fixed_seconds(ins))
                elif ins.op in (Op.UP, Op.DOWN):
                    self.set_output(Z_DOWN_OUTPUT, ins.op is Op.DOWN)
                    await self._sleep_on(due, fixed_seconds(ins))
                elif ins.op is Op.WRITEO:
                    self.set_output(ins.operands[0], bool(ins.operands[1]))
                elif ins.op is Op.WAITI:
                    await self._wait_input(ins.operands[0], bool(ins.operands[1]))
                    # An input that came later than the program got here: it goes on from now.
                    due[0] = max(due[0], clock.monotonic())
                elif ins.op is Op.SPEED:
                    self.speed_percent = ins.operands[0]
                elif ins.op is Op.BRANCH or (
                    ins.op is Op.TESTI
                    and DiDo(self.inputs, self.outputs).input(ins.operands[0])
                    == bool(ins.operands[1])
                ):
                    pc = ins.operands[-1]
                    # A loop of jumps takes no machine time: let the link and the I/O go on.
                    await clock.sleep(0)
                    due[0] = max(due[0], clock.monotonic())
                elif ins.op is Op.END:
                    run.outcome = "completed"
                    break
                if pc >= len(program.instructions):  # a program without END runs off its end
                    self._data_error(PROGRAMMING_ERROR)
                    run.outcome = "programming error"
                    break
        except asyncio.CancelledError:
            run.outcome = self._abort_reason
            raise
        finally:
            run.end = self.clock.monotonic()
            if self.state == 2:
                self.state = 1
