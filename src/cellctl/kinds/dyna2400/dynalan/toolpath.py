"""Toolpath: the motion a program makes, block by block, and how long it takes.

Usage::

    path = build_toolpath(split_program(program), MachineState.initial(Units.INS))
    path.machining_seconds, path.bounds(), path.block_seconds
    for tm in path.moves: tm.move.path, tm.block

Coordinates are the machine's reference coordinates in the program's units. Problems met on the
way (a move outside the travel, a statement that cannot run) are collected in ``faults``, not
raised, so one run reports them all; the validator turns them into problems.

Cost: the trace holds at most :data:`~cellctl.kinds.dyna2400.dynalan.table.TOOLPATH_POINTS_MAX`
points and executes at most :data:`~cellctl.kinds.dyna2400.dynalan.table.TOOLPATH_STEPS_MAX`
statements (REPEATs unrolled); a program that goes past either gets a ``size`` fault at the
line where it did and is traced no further, so memory and time stay bounded whatever motion
the program describes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from cellctl.kinds.dyna2400.dynalan.machine import (
    MachineConfig,
    MachineState,
    Move,
    MoveKind,
    ProgramFault,
    Vec,
    run_block,
    travel_fault,
)
from cellctl.kinds.dyna2400.dynalan.splitter import Block, BlockLine
from cellctl.kinds.dyna2400.dynalan.table import TOOLPATH_POINTS_MAX, TOOLPATH_STEPS_MAX, Units


@dataclass(frozen=True, slots=True)
class ToolpathMove:
    move: Move
    block: int  # 1-based block index


@dataclass(frozen=True, slots=True)
class Fault:
    """Something the controller would stop on, placed in the block and the file."""

    block: int
    number: int  # line number inside the block as sent
    origin: BlockLine | None  # the block line (its origin gives the file row)
    code: str
    message: str


@dataclass
class Toolpath:
    units: Units
    blocks: int = 0
    moves: list[ToolpathMove] = field(default_factory=list)
    faults: list[Fault] = field(default_factory=list)
    block_starts: list[Vec] = field(default_factory=list)  # tool position as each block begins
    block_seconds: list[float] = field(default_factory=list)
    operator_stops: int = 0  # SETUP statements: the operator must act

    @property
    def machining_seconds(self) -> float:
        """Estimated machining time: feed moves, rapid moves and dwells."""
        return sum(tm.move.seconds for tm in self.moves)

    def seconds(self, kind: MoveKind) -> float:
        return sum(tm.move.seconds for tm in self.moves if tm.move.kind is kind)

    def length(self, kind: MoveKind) -> float:
        return sum(tm.move.length for tm in self.moves if tm.move.kind is kind)

    def bounds(self) -> tuple[Vec, Vec]:
        """``(low corner, high corner)`` of everything the tool visits (start included)."""
        points = [p for tm in self.moves for p in tm.move.path] + self.block_starts
        if not points:
            return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
        low = (min(p[0] for p in points), min(p[1] for p in points), min(p[2] for p in points))
        high = (max(p[0] for p in points), max(p[1] for p in points), max(p[2] for p in points))
        return low, high


def build_toolpath(
    blocks: Sequence[Block],
    state: MachineState,
    config: MachineConfig | None = None,
    *,
    max_points: int = TOOLPATH_POINTS_MAX,
    max_steps: int = TOOLPATH_STEPS_MAX,
) -> Toolpath:
    """Run ``blocks`` one after the other from ``state`` (changed in place) and trace them.

    Stops with a ``size`` fault once the trace passes ``max_points`` points or ``max_steps``
    executed statements (see the module docstring).
    """
    config = config or MachineConfig()
    path = Toolpath(state.units, blocks=len(blocks))
    points = 0
    steps_left = max_steps
    for block in blocks:
        by_number = {line.number: line for line in block.lines}
        path.block_starts.append(state.position)
        before = len(path.moves)
        reported: set[int] = set()
        steps = 0
        try:
            for step in run_block(
                block.memory(),
                state,
                config,
                check_travel=False,
                skip_malformed=True,
                max_steps=steps_left,
            ):
                steps += 1
                if step.operator:
                    path.operator_stops += 1
                points += sum(len(move.path) for move in step.moves)
                if points > max_points:
                    raise ProgramFault(
                        "size",
                        f"the program's motion passes {max_points:,} points here: too much "
                        "to trace (REPEATs nested deep, or passes too fine?)",
                        step.number,
                    )
                for move in step.moves:
                    path.moves.append(ToolpathMove(move, block.index))
                fault = travel_fault(step.moves, state.units, config.travel)
                if fault and step.number not in reported:
                    reported.add(step.number)
                    origin = by_number.get(step.number)
                    path.faults.append(Fault(block.index, step.number, origin, "travel", fault))
        except ProgramFault as fault:
            number = fault.number if fault.number is not None else 0
            origin = by_number.get(number)
            code, message = fault.code, fault.message
            if code == "runaway":
                code = "size"
                message = (
                    f"the program runs more than {max_steps:,} lines (REPEATs unrolled): "
                    "a loop, or too much to trace"
                )
            path.faults.append(Fault(block.index, number, origin, code, message))
            if code == "size":
                path.block_seconds.append(sum(tm.move.seconds for tm in path.moves[before:]))
                break
        steps_left -= steps
        path.block_seconds.append(sum(tm.move.seconds for tm in path.moves[before:]))
    return path
