"""How long an IBM 7545 program takes: the arm's motion model, once. Pure, no I/O, no clock.

The robot emulator sleeps these times (divided by its time scale); the cell's physical bound
(:mod:`cellctl.cell.estimate`) adds them up without running anything::

    arm = ScaraArm()
    arm.move_seconds(arm.home, (500, -300, 0, 0))        # 0.36 s at full speed
    run = timeline(decode_program(body))                  # every input already there
    run.end_s, run.writes                                # END reached; every WRITEO, timed

The model (all **assumed**; the source gives no dynamics): a two-link SCARA arm (400 + 250 mm),
straight moves timed from the Cartesian distance at :data:`SPEED_MM_S` scaled by ``SPEED``
percent, the gripper and the Z cylinder :data:`GRIPPER_S` per switch, ``DELAY`` its own time,
and every other instruction instantaneous. ``WAITI`` takes what the cell makes it take: the
caller's ``input_ready`` says when the input reaches the value.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from cellctl.errors import UsageError
from cellctl.kinds.families import InputReady, ProgramRun
from cellctl.kinds.ibm7545.aml import Instruction, Op, decode_program
from cellctl.kinds.ibm7545.records import ProgramFile, encode_record

__all__ = [
    "GRIPPER_S",
    "SPEED_MM_S",
    "STOP_S",
    "ArmModel",
    "Point",
    "ScaraArm",
    "Timeline",
    "download_chars",
    "timeline",
]

Point = tuple[float, float, float, float]  # x, y, z in mm; roll in degrees

SPEED_MM_S = 500.0  # assumed full Cartesian speed of the arm
GRIPPER_S = 0.3  # assumed time for the gripper or the Z cylinder to switch
STOP_S = 0.5  # assumed time for a stopped cycle to wind down


@dataclass(frozen=True)
class ScaraArm:
    """Two-link SCARA geometry (assumed defaults; the source gives none).

    ``joints(x, y)`` solves the inverse kinematics; ``reachable`` is the workspace check.
    """

    link1_mm: float = 400.0
    link2_mm: float = 250.0
    z_min_mm: float = 0.0
    z_max_mm: float = 200.0
    roll_limit_deg: float = 360.0

    @property
    def home(self) -> Point:
        """Home: the arm stretched along +x, Z at 0, roll 0."""
        return (self.link1_mm + self.link2_mm, 0.0, 0.0, 0.0)

    def joints(self, x: float, y: float) -> tuple[float, float] | None:
        """Shoulder and elbow angles in degrees for (x, y), or None if out of reach."""
        l1, l2 = self.link1_mm, self.link2_mm
        c2 = (x * x + y * y - l1 * l1 - l2 * l2) / (2 * l1 * l2)
        if not -1.0 <= c2 <= 1.0:
            return None
        t2 = math.acos(c2)
        t1 = math.atan2(y, x) - math.atan2(l2 * math.sin(t2), l1 + l2 * math.cos(t2))
        return math.degrees(t1), math.degrees(t2)

    def reachable(self, point: Point) -> bool:
        """True when the point is inside the workspace."""
        x, y, z, roll = point
        return (
            self.joints(x, y) is not None
            and self.z_min_mm <= z <= self.z_max_mm
            and abs(roll) <= self.roll_limit_deg
        )


def move_seconds(a: Point, b: Point, speed_mm_s: float = SPEED_MM_S, percent: int = 100) -> float:
    """A straight move from ``a`` to ``b``: Cartesian distance over the speed in force."""
    return math.dist(a[:3], b[:3]) / (speed_mm_s * percent / 100)


def target(ins: Instruction, position: Point) -> Point:
    """Where a PMOVE or ZMOVE goes (operands in tenths)."""
    if ins.op is Op.PMOVE:
        a, b, c, d = ins.operands
        return (a / 10, b / 10, c / 10, d / 10)
    return (position[0], position[1], ins.operands[0] / 10, position[3])


def fixed_seconds(ins: Instruction) -> float:
    """Machine time of an instruction that does not move the arm (DELAY, gripper, Z)."""
    if ins.op is Op.DELAY:
        return ins.operands[0] / 10
    if ins.op in (Op.GRASP, Op.RELEASE, Op.UP, Op.DOWN):
        return GRIPPER_S
    return 0.0


#: One run of a program on the model (the family's record of a run).
Timeline = ProgramRun


def timeline(
    instructions: Sequence[Instruction],
    *,
    input_ready: InputReady | None = None,
    arm: ScaraArm | None = None,
    speed_mm_s: float = SPEED_MM_S,
    start: Point | None = None,
    max_steps: int = 100_000,
) -> Timeline:
    """Run ``instructions`` on the motion model from ``start`` (home) to END.

    ``input_ready`` (default: every input already there) times each WAITI and decides each
    TESTI (taken when the input has the value now). A point out of the workspace, a program
    that runs off its end or more than ``max_steps`` instructions raise :class:`UsageError`.
    """
    arm = arm or ScaraArm()
    ready = input_ready or (lambda port, value, now, run: now)
    position = start or arm.home
    percent = 100
    run = Timeline()
    now = 0.0
    pc = 0
    for _ in range(max_steps):
        if pc >= len(instructions):
            raise UsageError("the program runs off its end (no END)")
        ins = instructions[pc]
        pc += 1
        if ins.op in (Op.PMOVE, Op.ZMOVE):
            point = target(ins, position)
            if not arm.reachable(point):
                raise UsageError(f"{ins}: point out of workspace")
            seconds = move_seconds(position, point, speed_mm_s, percent)
            position = point
        else:
            seconds = fixed_seconds(ins)
        now += seconds
        run.motion_s += seconds
        if ins.op is Op.WRITEO:
            run.writes.append((now, ins.operands[0], bool(ins.operands[1])))
        elif ins.op is Op.WAITI:
            until = max(now, ready(ins.operands[0], bool(ins.operands[1]), now, run))
            run.wait_s += until - now
            now = until
        elif ins.op is Op.SPEED:
            percent = ins.operands[0]
        elif ins.op is Op.BRANCH:
            pc = ins.operands[-1]
        elif ins.op is Op.TESTI:
            if ready(ins.operands[0], bool(ins.operands[1]), now, run) <= now:
                pc = ins.operands[-1]
        elif ins.op is Op.END:
            run.end_s = now
            run.position = position
            return run
    raise UsageError(f"the program runs more than {max_steps:,} instructions")


def download_chars(program: ProgramFile) -> int:
    """Characters on the line for one download of ``program`` (N transaction): every record
    the host sends and the controller's Ack after the identifier and after each record, in
    turn (the host waits for each Ack, so both directions add up)."""
    sent = sum(len(encode_record(r)) for r in program.records)
    return sent + len(program.records) + 1


class ArmModel:
    """The robot kind's :class:`~cellctl.kinds.families.RobotModel`: programs as the cell's
    config holds them (program files), run on the arm's motion model."""

    def __init__(self, arm: ScaraArm | None = None) -> None:
        self.arm = arm or ScaraArm()

    def starts(self, programs: Iterable[Any]) -> list[Any]:
        ends = [timeline(_instructions(p), arm=self.arm).position for p in programs]
        return [self.arm.home, *dict.fromkeys(ends)]

    def run(self, program: Any, *, input_ready: InputReady, start: Any) -> ProgramRun:
        return timeline(_instructions(program), input_ready=input_ready, arm=self.arm, start=start)

    def download_chars(self, program: Any) -> int:
        return download_chars(program)


def _instructions(program: ProgramFile) -> list[Instruction]:
    return decode_program(r for r in program.records if r.ident == "D")
