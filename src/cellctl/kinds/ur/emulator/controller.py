"""The emulated controller: robot mode, safety, the running program, I/O. No sockets here.

It answers Dashboard Server lines (:meth:`UrController.answer`), runs URScript (a ``.urp``
on the robot after ``load`` and ``play``, or a script from the secondary interface, which
replaces what runs), and gives RTDE its fields (:meth:`UrController.sample`). Machine time
is divided by ``time_scale``: a 2 s move takes 2/time_scale s of the loop's time.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Iterator
from typing import Any

from cellctl.clock import Clock, current_clock, emulator_clock
from cellctl.emulators.switches import check_switch
from cellctl.errors import UsageError
from cellctl.kinds.ur.dashboard import (
    COMMANDS,
    LOCAL_MODE_REFUSAL,
    MOVING_SAFETY,
    NOT_UNDERSTOOD,
    POWER_ON_BIT,
    PROGRAM_RUNNING_BIT,
    STATUS_BITS,
    RobotMode,
    RuntimeState,
    SafetyStatus,
    split_command,
)
from cellctl.kinds.ur.motion import ARMS, HOME, Joints, interpolate
from cellctl.kinds.ur.rtde import ControllerVersion
from cellctl.kinds.ur.urscript import Move, ScriptError, Sleep, Step, parse, run

#: The emulator's fault switches (``--fault NAME``; the operator's remedy in brackets).
FAULTS: dict[str, str] = {
    "protective_stop": "a protective stop: the program pauses, the arm stops "
    "(unlock protective stop, 5 s after it, then play)",
    "estop": "an emergency stop: the program stops, brakes engage (clear it: the button "
    "released; then close safety popup, brake release)",
    "power_off": "the arm's power goes off: the program stops (power on, brake release)",
    "never_ends": "a program that never ends: each program plays, stuck before its first line",
    "local_mode": "the pendant in local mode: acting commands and scripts are refused",
    "drop": "every connection dropped now (the controller keeps its state)",
}
#: Seconds (machine time) from ``power on`` to IDLE, and from ``brake release`` to RUNNING.
POWER_ON_S = 2.0
BRAKE_RELEASE_S = 1.5
#: A protective stop can be unlocked this many seconds after it (UR's rule).
UNLOCK_AFTER_S = 5.0
#: Joint modes (RTDE ``joint_mode``).
JOINT_RUNNING, JOINT_IDLE, JOINT_POWER_OFF = 253, 255, 239
#: Standard digital inputs and outputs (0-7), configurable (8-15), tool (16-17).
DIGITAL_PORTS = 18


class UrController:
    """One UR controller's state (see module docstring)."""

    def __init__(
        self,
        *,
        time_scale: float | None = None,
        clock: Clock | None = None,
        model: str = "UR5e",
        version: ControllerVersion | None = None,
        programs: dict[str, str] | None = None,
    ) -> None:
        self._clock = emulator_clock(clock, time_scale)
        if model not in ARMS:
            raise UsageError(f"unknown UR model {model!r}; known: {', '.join(ARMS)}")
        self.arm = ARMS[model]
        self.version = version or ControllerVersion(5, 15, 0, 1)
        self.programs: dict[str, str] = dict(programs or {})
        self.mode = RobotMode.POWER_OFF
        self.safety = SafetyStatus.NORMAL
        self.runtime = RuntimeState.STOPPED
        self.loaded: str | None = None
        self.remote = True
        self.faults: dict[str, str | None] = {}
        self.inputs = 0
        self.outputs = 0
        self.out_registers = [0] * 48
        self.in_registers = [0] * 48
        self.out_doubles = [0.0] * 48
        self.messages: list[str] = []
        self.output_hooks: list[Callable[[int, bool], None]] = []
        self.runs: list[str] = []  # each program started, by name (tests, the emulated cell)
        self.scripts_refused = 0
        self._q: Joints = HOME
        self._pose: tuple[Joints, Any] | None = None  # the last joints and their TCP pose
        self._move: tuple[float, Move] | None = None  # (loop time it started, move)
        self._task: asyncio.Task[None] | None = None
        self._resume = asyncio.Event()
        self._resume.set()
        self._stopped_at = 0.0
        self._mode_task: asyncio.Task[None] | None = None
        self._rest: Move | None = None  # a move a pause cut short: its rest, for the resume
        self.on_drop: list[Callable[[], None]] = []
        self.started_at = self._now()

    # -- time -------------------------------------------------------------------------------------

    @property
    def clock(self) -> Clock:
        """What the controller times its moves on: the clock given, else the running loop's."""
        return self._clock or current_clock()

    @property
    def time_scale(self) -> float:
        """Seconds of machine time per second of its clock."""
        return self.clock.time_scale

    @time_scale.setter
    def time_scale(self, value: float) -> None:
        self._clock = emulator_clock(None, value)  # shorthand for RealClock(value)

    def _now(self) -> float:
        return self.clock.monotonic()

    def machine_s(self, real_s: float) -> float:
        return real_s * self.time_scale

    @property
    def q(self) -> Joints:
        """The joints now: part way along the move that runs."""
        if self._move is None:
            return self._q
        started, move = self._move
        if move.seconds <= 0:
            return move.end
        fraction = self.machine_s(self._now() - started) / move.seconds
        return interpolate(move.start, move.end, fraction)

    @q.setter
    def q(self, value: Joints) -> None:
        self._q = value

    # -- I/O --------------------------------------------------------------------------------------

    def digital_in(self, n: int) -> bool:
        return bool(self.inputs >> n & 1)

    def digital_out(self, n: int) -> bool:
        return bool(self.outputs >> n & 1)

    def set_input(self, n: int, value: bool | int) -> None:
        """A digital input (0-17) as the cell's wiring drives it."""
        if not 0 <= n < DIGITAL_PORTS:
            raise UsageError(f"digital input {n}: 0 to {DIGITAL_PORTS - 1}")
        self.inputs = self.inputs | 1 << n if value else self.inputs & ~(1 << n)

    def set_digital_out(self, n: int, value: bool) -> None:
        if not 0 <= n < DIGITAL_PORTS:
            raise ScriptError(f"Runtime error: digital output {n} does not exist")
        before = self.digital_out(n)
        self.outputs = self.outputs | 1 << n if value else self.outputs & ~(1 << n)
        if before != value:
            for hook in list(self.output_hooks):
                hook(n, value)

    def write_register(self, n: int, value: int) -> None:
        if not 0 <= n < 48:
            raise ScriptError(f"Runtime error: output integer register {n} does not exist")
        self.out_registers[n] = value

    def read_register(self, n: int) -> int:
        if not 0 <= n < 48:
            raise ScriptError(f"Runtime error: input integer register {n} does not exist")
        return self.in_registers[n]

    def message(self, text: str) -> None:
        self.messages.append(text)

    # -- faults -----------------------------------------------------------------------------------

    def set_fault(self, name: str, arg: str | None = None) -> None:
        """Switch a fault on (names in :data:`FAULTS`)."""
        check_switch(FAULTS, name, arg)
        if name == "drop":
            for drop in list(self.on_drop):
                drop()
            return
        self.faults[name] = arg
        if name == "protective_stop":
            self.safety = SafetyStatus.PROTECTIVE_STOP
            self._stopped_at = self._now()
            self._halt_motion(pause=True)
        elif name == "estop":
            self.safety = SafetyStatus.ROBOT_EMERGENCY_STOP
            self._halt_motion(pause=False)
            if self.mode == RobotMode.RUNNING:
                self.mode = RobotMode.IDLE
        elif name == "power_off":
            self._halt_motion(pause=False)
            self.mode = RobotMode.POWER_OFF
        elif name == "local_mode":
            self.remote = False

    def clear_fault(self, name: str) -> None:
        """Switch a fault off: the e-stop button released, remote control back, programs
        that end. A protective stop stays until ``unlock protective stop``."""
        check_switch(FAULTS, name, None)
        self.faults.pop(name, None)
        if name == "estop" and self.safety in (
            SafetyStatus.ROBOT_EMERGENCY_STOP,
            SafetyStatus.SYSTEM_EMERGENCY_STOP,
        ):
            self.safety = SafetyStatus.NORMAL
        elif name == "local_mode":
            self.remote = True

    def _halt_motion(self, *, pause: bool) -> None:
        q = self.q
        if self._move is not None:
            # Keep the rest of the move for a resume.
            started, move = self._move
            done = self.machine_s(self._now() - started)
            rest = max(0.0, move.seconds - done)
            self._move = None
            self._q = q
            self._rest = Move(rest, q, move.end, move.linear) if pause else None
        if self._task is None or self._task.done():
            return
        if pause:
            self.runtime = RuntimeState.PAUSED
            self._resume.clear()
        else:
            self._cancel_program()

    # -- programs ---------------------------------------------------------------------------------

    def start_program(self, name: str, text: str) -> None:
        """Run ``text`` now, replacing what runs."""
        self._cancel_program()
        program = parse(text)
        self.runtime = RuntimeState.PLAYING
        self._resume.set()
        self._rest = None
        self.runs.append(name)
        self._task = asyncio.ensure_future(self._run(program))

    def _cancel_program(self) -> None:
        task, self._task = self._task, None
        if task is not None and not task.done():
            task.cancel()
        if self._move is not None:
            self._q, self._move = self.q, None
        self.runtime = RuntimeState.STOPPED
        self._resume.set()

    async def _run(self, program: Any) -> None:
        try:
            # A program that never ends is stuck before its first line (as one waiting for
            # an input that never comes): nothing of it, its end register included, happens.
            while "never_ends" in self.faults:
                await self._take(Sleep(1.0))
            steps: Iterator[Step] = run(program, self, self.arm)
            for step in steps:
                await self._take(step)
        except ScriptError as e:
            self.messages.append(str(e))
        except asyncio.CancelledError:
            raise
        if self._task is asyncio.current_task():
            self._task = None
            self.runtime = RuntimeState.STOPPED

    async def _take(self, step: Step) -> None:
        await self._resume.wait()
        if isinstance(step, Sleep):
            end = self.clock.monotonic() + step.seconds / self.time_scale
            while True:
                await self._resume.wait()
                left = end - self.clock.monotonic()
                if left <= 0:
                    return
                await self.clock.sleep(left)
            return
        move: Move | None = step
        while move is not None:
            await self._resume.wait()
            self._move = (self.clock.monotonic(), move)
            await self.clock.sleep(move.seconds / self.time_scale)
            if self._move is not None and self._move[1] is move:
                self._q, self._move = move.end, None
                return
            move = getattr(self, "_rest", None)  # paused mid-move: the rest after resume
            self._rest = None

    # -- the Dashboard Server ---------------------------------------------------------------------

    def answer(self, line: str) -> str:
        """The Dashboard Server's answer to one line (its state changed as the line says)."""
        # What the line names comes back as it came, but never a line break in an answer.
        line = "".join(c if c.isprintable() else ascii(c)[1:-1] for c in line.strip())
        command, arg = split_command(line)
        if command is None:
            return NOT_UNDERSTOOD.format(line=line)
        if command.acts and not self.remote and self.version.e_series:
            return LOCAL_MODE_REFUSAL
        handler = getattr(self, "_cmd_" + command.text.replace(" ", "_"), None)
        if handler is None:
            return command.success[0]
        result: str = handler(arg)
        return result

    def _cmd_load(self, arg: str) -> str:
        if arg not in self.programs:
            return f"File not found: {arg}"
        if self.runtime != RuntimeState.STOPPED:
            return f"Error while loading program: {arg}"
        self.loaded = arg
        return f"Loading program: {arg}"

    def _cmd_play(self, arg: str) -> str:
        if self.mode != RobotMode.RUNNING or self.safety not in MOVING_SAFETY:
            return "Failed to execute: play"
        if self.runtime == RuntimeState.PAUSED and self._task is not None:
            self.runtime = RuntimeState.PLAYING  # a paused program goes on, whoever sent it
            self._resume.set()
        elif self.loaded is None:
            return "Failed to execute: play"
        elif self.runtime == RuntimeState.STOPPED:
            self.start_program(self.loaded, self.programs[self.loaded])
        return "Starting program"

    def _cmd_stop(self, arg: str) -> str:
        self._cancel_program()
        return "Stopped"

    def _cmd_pause(self, arg: str) -> str:
        if self.runtime != RuntimeState.PLAYING:
            return "Failed to execute: pause"
        self._halt_motion(pause=True)
        return "Pausing program"

    def _cmd_running(self, arg: str) -> str:
        return f"Program running: {'true' if self.runtime == RuntimeState.PLAYING else 'false'}"

    def _cmd_robotmode(self, arg: str) -> str:
        return f"Robotmode: {self.mode.text}"

    def _cmd_get_loaded_program(self, arg: str) -> str:
        return f"Loaded program: {self.loaded}" if self.loaded else "No program loaded"

    def _cmd_programState(self, arg: str) -> str:
        state = RuntimeState.PAUSED if self.runtime == RuntimeState.PAUSING else self.runtime
        if state not in (RuntimeState.PLAYING, RuntimeState.PAUSED):
            state = RuntimeState.STOPPED
        return f"{state.text} {self.loaded or '<unnamed>'}"

    def _cmd_isProgramSaved(self, arg: str) -> str:
        return f"true {self.loaded or '<unnamed>'}"

    def _cmd_PolyscopeVersion(self, arg: str) -> str:
        return f"URSoftware {self.version.major}.{self.version.minor}.{self.version.bugfix}"

    def _cmd_power_on(self, arg: str) -> str:
        if self.mode == RobotMode.POWER_OFF:
            self.mode = RobotMode.POWER_ON
            self._later(POWER_ON_S, RobotMode.POWER_ON, RobotMode.IDLE)
        return "Powering on"

    def _cmd_power_off(self, arg: str) -> str:
        self._cancel_program()
        self.mode = RobotMode.POWER_OFF
        return "Powering off"

    def _cmd_brake_release(self, arg: str) -> str:
        if self.mode == RobotMode.IDLE and self.safety in MOVING_SAFETY:
            self._later(BRAKE_RELEASE_S, RobotMode.IDLE, RobotMode.RUNNING)
        return "Brake releasing"

    def _later(self, seconds: float, from_mode: RobotMode, to_mode: RobotMode) -> None:
        async def change() -> None:
            await self.clock.sleep(seconds / self.time_scale)
            if self.mode == from_mode:
                self.mode = to_mode

        self._mode_task = asyncio.ensure_future(change())

    def _cmd_safetymode(self, arg: str) -> str:
        return f"Safetymode: {self.safety.text}"

    def _cmd_safetystatus(self, arg: str) -> str:
        return f"Safetystatus: {self.safety.text}"

    def _cmd_unlock_protective_stop(self, arg: str) -> str:
        if self.safety == SafetyStatus.PROTECTIVE_STOP:
            if self.machine_s(self._now() - self._stopped_at) < UNLOCK_AFTER_S:
                return COMMANDS["unlock protective stop"].failure[0]
            self.safety = SafetyStatus.NORMAL
            self.faults.pop("protective_stop", None)
        return "Protective stop releasing"

    def _cmd_is_in_remote_control(self, arg: str) -> str:
        return "true" if self.remote else "false"

    def _cmd_get_robot_model(self, arg: str) -> str:
        return self.arm.name.removesuffix("e")

    def _cmd_get_serial_number(self, arg: str) -> str:
        return "20255300000"

    # -- the secondary interface ------------------------------------------------------------------

    def script(self, text: str) -> bool:
        """A program from the secondary interface: runs now, replacing what runs; refused
        (False, told in the log) in local mode or while the arm cannot move."""
        if not self.remote and self.version.e_series:
            self.scripts_refused += 1
            self.messages.append("script refused: the robot is in local control")
            return False
        if self.mode != RobotMode.RUNNING or self.safety not in MOVING_SAFETY:
            self.scripts_refused += 1
            self.messages.append(f"script refused: robot mode {self.mode.text}")
            return False
        program = parse(text)
        name = program.entry.text[4:].split("(", 1)[0] if program.entry else "script"
        self.start_program(name.strip(), text)
        return True

    # -- RTDE -------------------------------------------------------------------------------------

    def sample(self) -> dict[str, Any]:
        """Every RTDE output field now."""
        q = self.q
        moving = self._move is not None
        powered = self.mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
        joint = (
            JOINT_RUNNING
            if self.mode == RobotMode.RUNNING
            else JOINT_IDLE
            if powered
            else JOINT_POWER_OFF
        )
        status_bits = (POWER_ON_BIT if powered else 0) | (
            PROGRAM_RUNNING_BIT if self.runtime == RuntimeState.PLAYING else 0
        )
        # The arm at rest keeps its pose: computed again only when the joints moved.
        if self._pose is None or self._pose[0] != q:
            self._pose = (q, self.arm.tcp(q))
        pose = self._pose[1]
        values: dict[str, Any] = {
            "timestamp": self._now() - self.started_at,
            "target_q": q,
            "target_qd": (0.0,) * 6,
            "actual_q": q,
            "actual_qd": (0.0,) * 6,
            "actual_TCP_pose": pose,
            "target_TCP_pose": pose,
            "actual_TCP_speed": (0.0,) * 6,
            "joint_mode": (joint,) * 6,
            "robot_mode": int(self.mode),
            "safety_mode": int(self.safety),
            "safety_status": int(self.safety),
            "runtime_state": int(self.runtime),
            "robot_status_bits": status_bits,
            "safety_status_bits": STATUS_BITS.get(self.safety, 0),
            "actual_digital_input_bits": self.inputs,
            "actual_digital_output_bits": self.outputs,
            "speed_scaling": 0.0 if not moving else 1.0,
            "target_speed_fraction": 1.0,
            "actual_execution_time": 0.1,
            "output_bit_registers0_to_31": 0,
            "output_bit_registers32_to_63": 0,
        }
        for n in range(48):
            values[f"output_int_register_{n}"] = self.out_registers[n]
            values[f"output_double_register_{n}"] = self.out_doubles[n]
        return values

    def take_inputs(self, values: dict[str, Any]) -> None:
        """An RTDE input package: digital outputs under their mask, input registers."""
        mask = int(values.get("standard_digital_output_mask", 0))
        if mask:
            value = int(values.get("standard_digital_output", 0))
            for n in range(8):
                if mask >> n & 1:
                    self.set_digital_out(n, bool(value >> n & 1))
        for key, value in values.items():
            if key.startswith("input_int_register_"):
                self.in_registers[int(key.rsplit("_", 1)[1])] = int(value)

    async def close(self) -> None:
        self._cancel_program()
        for task in (self._mode_task,):
            if task is not None and not task.done():
                task.cancel()
                with contextlib.suppress(BaseException):
                    await task
