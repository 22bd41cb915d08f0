"""A UR's timing model for bounds from physics (:class:`~cellctl.kinds.families.RobotModel`):
the program run on the same interpreter and motion model the emulator runs, in machine
seconds, its inputs as the cell's machinery gives them. No I/O, no clock::

    model = UrTiming(ARMS["UR5e"])
    run = model.run(program, input_ready=ready, start=HOME)   # run.end_s, run.writes
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from cellctl.kinds.families import InputReady, ProgramRun
from cellctl.kinds.ur.motion import ARMS, HOME, Arm, Joints
from cellctl.kinds.ur.program import UrProgram
from cellctl.kinds.ur.urscript import ScriptError, parse, run

#: A run stops counting here (a program waiting for an input that never comes).
LIMIT_S = 3600.0


class _Timed:
    """The environment a modelled run reads: inputs when the machinery gives them."""

    def __init__(self, start: Joints, input_ready: InputReady, record: ProgramRun) -> None:
        self.q = start
        self.now = 0.0
        self.input_ready = input_ready
        self.record = record
        self.outputs: dict[int, bool] = {}

    def digital_in(self, n: int) -> bool:
        return self.input_ready(n, True, self.now, self.record) <= self.now

    def digital_out(self, n: int) -> bool:
        return self.outputs.get(n, False)

    def set_digital_out(self, n: int, value: bool) -> None:
        self.outputs[n] = value
        self.record.writes.append((self.now, n, value))

    def write_register(self, n: int, value: int) -> None:
        pass

    def read_register(self, n: int) -> int:
        return 0

    def message(self, text: str) -> None:
        pass


class UrTiming:
    """The robot family's timing model for a UR of ``arm``."""

    def __init__(self, arm: Arm | None = None) -> None:
        self.arm = arm or ARMS["UR5e"]

    def starts(self, programs: Iterable[Any]) -> list[Any]:
        """Home, and where each program leaves the arm."""
        out: list[Any] = [HOME]
        for program in programs:
            end = self.run(program, input_ready=lambda p, v, now, r: now, start=HOME).position
            if end not in out:
                out.append(end)
        return out

    def run(self, program: Any, *, input_ready: InputReady, start: Any) -> ProgramRun:
        """``program`` (a :class:`UrProgram`) from ``start``: a ``.urp`` on the robot has no
        text here and counts as taking no time (the bound stays below any real run)."""
        record = ProgramRun(position=start)
        if not isinstance(program, UrProgram) or program.on_robot:
            return record
        env = _Timed(start, input_ready, record)
        try:
            for step in run(parse(program.text), env, self.arm):
                env.now += step.seconds
                # The arm's own work; a sleep polling an input is told apart by nothing here.
                record.motion_s += step.seconds
                if env.now > LIMIT_S:
                    break
        except ScriptError:
            pass
        record.end_s = env.now
        record.position = env.q
        return record

    def download_chars(self, program: Any) -> int:
        """Characters of one program sent to the robot (the secondary interface)."""
        return len(program.sendable(24, 1)) if isinstance(program, UrProgram) else 0
