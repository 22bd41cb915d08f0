"""DYNALAN validator: every problem of a program, before a byte goes out.

Usage::

    result = validate(parse_program(text, name="PART.DYN"), ValidationContext(units=Units.INS))
    for problem in result.problems:          # errors and warnings, in file order
        print(problem.format("PART.DYN"))
    if result.ok:
        send(result.blocks)                  # the program split into blocks, ready to send

Errors are what the controller would choke on or what would hurt the machine (the real
controller cannot detect a malformed program: a wrong file puts it into an error condition).
Warnings are legal but probably not what was meant. The checks: line-number order and range,
unknown statements and bad numbers (from the parser), feed rate range, continuation lines,
SKIP TO targets, REPEAT balance, arcs over 180 degrees, moves outside the travel (the program
is run from the tool at the reference zero), INS/MM mix-ups, and whether it splits into blocks.
"""

from __future__ import annotations

import re
from bisect import bisect_right
from dataclasses import dataclass, field, replace

from cellctl.kinds.dyna2400.dynalan.machine import MachineConfig, MachineState
from cellctl.kinds.dyna2400.dynalan.model import Line, Problem, Program, ProgramRole, Severity
from cellctl.kinds.dyna2400.dynalan.parser import is_block_end
from cellctl.kinds.dyna2400.dynalan.splitter import Block, SplitError, split_program
from cellctl.kinds.dyna2400.dynalan.table import (
    ARC_MAX_DEGREES,
    BLOCK_END_LINE,
    DECIMALS,
    FEED_MAX,
    FEED_MIN,
    MOTION_KINDS,
    PROGRAM_NUMBER_MAX,
    PROGRAM_NUMBER_MIN,
    REPEAT_MAX,
    SPINDLE_MAX_RPM,
    TOOL_MAX,
    Kind,
    Units,
    scale,
)
from cellctl.kinds.dyna2400.dynalan.toolpath import Toolpath, build_toolpath


@dataclass(frozen=True)
class ValidationContext:
    """What the validator knows about the machine.

    ``units``: the units the machine was set up in (its setup program's START), None if unknown.
    ``initial``: the machine state before the program (after the setup program); by default the
    tool at the reference zero with default feed rates.
    """

    role: ProgramRole = ProgramRole.AUTO
    units: Units | None = None
    config: MachineConfig = field(default_factory=MachineConfig)
    initial: MachineState | None = None


@dataclass
class Validation:
    """The outcome: problems in file order, the blocks to send and the toolpath (when it split)."""

    program: Program
    role: ProgramRole
    problems: list[Problem]
    blocks: list[Block] | None = None
    toolpath: Toolpath | None = None

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity is Severity.ERROR]

    @property
    def warnings(self) -> list[Problem]:
        return [p for p in self.problems if p.severity is Severity.WARNING]

    @property
    def ok(self) -> bool:
        return not self.errors


def resolve_role(program: Program, role: ProgramRole) -> ProgramRole:
    """AUTO becomes SETUP when the program has SETUP, END when it is only END, else MILLING."""
    if role is not ProgramRole.AUTO:
        return role
    kinds = {line.kind for line in program.lines}
    if Kind.SETUP in kinds:
        return ProgramRole.SETUP
    if Kind.END in kinds and kinds <= {Kind.END, Kind.COMMENT, Kind.BLANK}:
        return ProgramRole.END
    return ProgramRole.MILLING


_NUMBER_TOKEN = re.compile(r"(?<![\w.])[+-]?\d*\.(\d+)")


class _Checker:
    def __init__(self, program: Program, context: ValidationContext, role: ProgramRole) -> None:
        self.program = program
        self.context = context
        self.role = role
        self.units = program.units or context.units or Units.INS
        self.problems: list[Problem] = list(program.problems)
        self.drill_seen = False  # a DRIL line came before the current one
        self.opener: Line | None = None  # the last line of the segment that axis lines follow
        self.local_zero = False  # ZERO AT is in effect in the segment (no >REF COORD since)

    def add(
        self, severity: Severity, code: str, line: Line, message: str, token: str | None = None
    ) -> None:
        self.problems.append(
            Problem(severity, code, message, line.row, _column(line, token), line.label, line.block)
        )

    def error(self, code: str, line: Line, message: str, token: str | None = None) -> None:
        self.add(Severity.ERROR, code, line, message, token)

    def warn(self, code: str, line: Line, message: str, token: str | None = None) -> None:
        self.add(Severity.WARNING, code, line, message, token)

    # ---- per line ------------------------------------------------------------------------------
    def run(self) -> None:
        lines = self.program.lines
        if not lines:
            self.problems.append(Problem(Severity.ERROR, "empty", "the program has no lines", 1, 1))
            return
        segment: list[Line] = []
        for index, line in enumerate(lines):
            self.line(index, line, segment)
            segment.append(line)
            if is_block_end(line):
                self.close_segment(segment[:-1], closed=True)
                segment = []
                self.opener = None
                self.local_zero = False
        if segment:
            self.close_segment(segment, closed=False)
        self.role_checks()

    def line(self, index: int, line: Line, segment: list[Line]) -> None:
        prev = segment[-1] if segment else None
        if prev is not None and line.number <= prev.number:
            wrapped = prev.number >= BLOCK_END_LINE and line.number < 100
            if not wrapped:
                self.error(
                    "line-order",
                    line,
                    f"line {line.label} comes after {prev.label}: numbers increase within a block",
                    line.label,
                )
        stmt = line.statement
        if stmt is None:
            return
        kind = stmt.kind
        opener, self.opener = self.opener, self.opener if kind in _TRANSPARENT else line
        local_zero = self.local_zero
        if kind is Kind.ZERO_AT:
            self.local_zero = True
        elif kind is Kind.REF_COORD:
            self.local_zero = False
        if kind is Kind.DRILL:
            self.drill_seen = True
        self.precision(line)
        if is_block_end(line) and (prev is None or not _is_skip_900(prev)):
            self.error(
                "block-end",
                line,
                "the line before 900 must be SKIP TO 900: the controller runs a block once it "
                "has seen both",
            )
        if kind is Kind.START:
            if index != 0 or line.number != 0:
                self.error("start", line, "START belongs on line 000, the first of the program")
            units = Units(stmt.text["units"])
            if self.program.units is not None and units is not self.program.units:
                self.error(
                    "units-mix",
                    line,
                    f"START {units.value} after START {self.program.units.value}: "
                    "one program, one unit",
                    units.value,
                )
            elif self.context.units is not None and units is not self.context.units:
                self.error(
                    "units-mix",
                    line,
                    f"the program is in {units.value} but the machine was set up in "
                    f"{self.context.units.value}",
                    units.value,
                )
            number = int(stmt.value("program"))
            if not PROGRAM_NUMBER_MIN <= number <= PROGRAM_NUMBER_MAX:
                self.error("range", line, f"program number {number} outside 01-99")
        elif kind is Kind.SETUP and self.role is ProgramRole.MILLING:
            self.warn("setup", line, "SETUP in a milling program stops for the operator")
        elif kind is Kind.TOOL and stmt.value("tool") > TOOL_MAX:
            self.error("range", line, f"tool {stmt.value('tool'):g} above {TOOL_MAX}")
        elif kind is Kind.TD and stmt.value("diameter") <= 0:
            self.error("range", line, "tool diameter must be above 0")
        elif kind is Kind.FEED:
            self.feed(line, stmt.value("rate"))
        elif kind in (Kind.GO, Kind.GR, Kind.GO_FAST, Kind.GR_FAST) and len(stmt.words) != 1:
            axis = stmt.words[1][0]
            self.error(
                "axis-words",
                line,
                f"{kind.value} takes one axis word a line: put {axis} on a continuation line",
                axis,
            )
        elif kind is Kind.AXIS:
            self.axis_line(line, opener)
        elif kind is Kind.ARC:
            degrees = stmt.value("degrees")
            if abs(degrees) > ARC_MAX_DEGREES:
                self.error(
                    "arc",
                    line,
                    f"arc of {degrees:g} degrees: at most {ARC_MAX_DEGREES:g} a move "
                    "(use two GR A lines)",
                )
            elif degrees == 0:
                self.warn("arc", line, "arc of 0 degrees does nothing")
            if not local_zero:
                self.warn("arc", line, "arc about the reference zero: no ZERO AT before it")
        elif kind is Kind.SPINDLE_SPEED and stmt.value("rpm") > SPINDLE_MAX_RPM:
            self.error("range", line, f"spindle {stmt.value('rpm'):g} RPM above 10,000 RPM")
        elif kind is Kind.DWELL and stmt.value("seconds") < 0:
            self.error("range", line, "DWELL takes a time of 0 seconds or more")
        elif kind is Kind.DRILL and stmt.value("peck") < 0:
            self.error("range", line, "PECK= takes 0 (one plunge) or a positive depth")
        elif kind in (Kind.DRILL_TOP, Kind.DRILL_BOTTOM):
            if not self.drill_seen:
                self.error("drill", line, f"{kind.value} without DRIL PECK= before it")
        elif kind is Kind.REPEAT and not 1 <= stmt.value("count") <= REPEAT_MAX:
            self.error("range", line, f"REPEAT count {stmt.value('count'):g} outside 1-99")
        elif kind is Kind.END and self.role is ProgramRole.MILLING:
            self.warn(
                "end",
                line,
                "END returns the controller to manual mode: send it with `cellctl mill end`",
            )
        elif kind in (Kind.RPOCKET, Kind.FRAME, Kind.RFRAME):
            if stmt.value("XL") == 0 or stmt.value("YL") == 0:
                self.error("cycle", line, f"{kind.value} needs XL= and YL= other than 0")
        elif kind is Kind.ARCFRAME and abs(stmt.value("A")) > 360:
            self.error("cycle", line, "ARCFRAME sweeps at most 360 degrees")
        if "DP" in stmt.values and not stmt.values["DP"] > 0:
            self.error("cycle", line, "DP= (depth a pass) must be above 0", "DP")

    def feed(self, line: Line, rate: float) -> None:
        low, high = scale(FEED_MIN, self.units), scale(FEED_MAX, self.units)
        if low <= rate <= high:
            return
        unit = f"{self.units.length_name}/min"
        hint = ""
        if self.units is Units.INS and scale(FEED_MIN, Units.MM) <= rate <= scale(
            FEED_MAX, Units.MM
        ):
            hint = " (a mm/min value in an INS program?)"
        elif self.units is Units.MM and FEED_MIN <= rate < low:
            hint = " (an in/min value in an MM program?)"
        self.error(
            "feed-range",
            line,
            f"feed rate {rate:g} {unit} outside {low:g}-{high:g} {unit}{hint}",
            f"{line.raw.split('=')[-1].strip()}",
        )

    def precision(self, line: Line) -> None:
        limit = DECIMALS[self.units.value]
        for match in _NUMBER_TOKEN.finditer(line.raw[3:]):
            if len(match.group(1)) > limit:
                self.warn(
                    "precision",
                    line,
                    f"{match.group().strip()} has more than {limit} decimals: the controller "
                    "rounds it",
                    match.group().strip(),
                )
                return

    def axis_line(self, line: Line, opener: Line | None) -> None:
        assert line.statement is not None
        words = line.statement.words
        kind = opener.kind if opener else None
        if kind in MOTION_KINDS or kind is Kind.ZERO_AT:
            if len(words) != 1:
                self.error(
                    "continuation",
                    line,
                    "a continuation line carries one axis word",
                    words[1][0] if len(words) > 1 else None,
                )
        elif kind is Kind.DRILL_BOTTOM:
            if any(axis == "Z" for axis, _ in words):
                self.error("drill", line, "a hole line gives X and Y only", "Z")
        else:
            self.error(
                "continuation",
                line,
                "axis-only line without a GO/GR, ZERO AT or ZD= line before it",
            )

    # ---- per block -----------------------------------------------------------------------------
    def close_segment(self, items: list[Line], *, closed: bool) -> None:
        if self.role is ProgramRole.END:
            return
        if not closed and items:
            self.warn(
                "unclosed-block",
                items[-1],
                "the last block is not closed by SKIP TO 900 / 900 (cellctl closes it when "
                "sending)",
            )
        stack: list[int] = []
        frames: list[int] = []  # the innermost REPEAT around each line (-1: none)
        for i, line in enumerate(items):
            if line.kind is Kind.REPEAT_END:
                if stack:
                    stack.pop()
                else:
                    self.error("repeat", line, "REPEAT END without a REPEAT before it")
            frames.append(stack[-1] if stack else -1)
            if line.kind is Kind.REPEAT:
                stack.append(i)
        for i in stack:
            self.error("repeat", items[i], "REPEAT without a REPEAT END in its block")
        rows: dict[int, list[int]] = {}
        for i, line in enumerate(items):
            rows.setdefault(line.number, []).append(i)
        for i, line in enumerate(items):
            if line.kind is not Kind.SKIP:
                continue
            assert line.statement is not None
            target = int(line.statement.value("target"))
            if target == BLOCK_END_LINE:
                if frames[i] >= 0:
                    self.error("skip", line, "SKIP TO 900 from inside a REPEAT leaves it open")
                continue
            places = rows.get(target, [])
            after = bisect_right(places, i)
            found = places[after] if after < len(places) else None
            if found is None:
                if after > 0:
                    self.error(
                        "skip",
                        line,
                        f"SKIP TO {target:03d} jumps backwards: the block would never end",
                        f"{target:03d}",
                    )
                else:
                    self.error(
                        "skip",
                        line,
                        f"SKIP TO {target:03d}: no line {target:03d} in this block",
                        f"{target:03d}",
                    )
            elif frames[i] != frames[found]:
                self.error(
                    "skip",
                    line,
                    f"SKIP TO {target:03d} jumps into or out of a REPEAT",
                    f"{target:03d}",
                )

    def role_checks(self) -> None:
        if self.role is ProgramRole.END:
            ends = [line for line in self.program.lines if line.kind is Kind.END]
            if not ends:
                first = self.program.lines[0]
                self.error("end", first, "the end program must hold END")
        if self.role is ProgramRole.SETUP and not any(
            line.kind is Kind.SETUP for line in self.program.lines
        ):
            self.error("setup", self.program.lines[0], "a setup program must hold SETUP")

    # ---- simulation ------------------------------------------------------------------------------
    def simulate(self) -> tuple[list[Block] | None, Toolpath | None]:
        if self.role is ProgramRole.END:
            return None, None
        try:
            blocks = split_program(self.program)
        except SplitError as exc:
            self.problems.append(Problem(Severity.ERROR, "split", str(exc), exc.row, exc.column))
            return None, None
        state = (self.context.initial or MachineState.initial(self.units)).copy()
        state.set_units(self.units)
        path = build_toolpath(blocks, state, self.context.config)
        # Static checks already explain most runtime faults; report a row once.
        rows = {p.row for p in self.problems if p.severity is Severity.ERROR}
        for fault in path.faults:
            origin = fault.origin.origin if fault.origin else None
            if origin is not None and origin.row in rows:
                continue
            message = fault.message
            if fault.code == "travel" and self.units is Units.INS and _fits_in_mm(fault.message):
                message += " (values in mm in an INS program?)"
            if origin is None:
                self.problems.append(
                    Problem(Severity.ERROR, fault.code, message, 1, 1, block=fault.block)
                )
            else:
                self.error(fault.code, origin, message)
        return blocks, path


_TRAVEL_VALUE = re.compile(r"^([XYZ]) (\S+) is outside the [XYZ] travel (\S+) to (\S+)")


def _fits_in_mm(message: str) -> bool:
    """Whether the out-of-travel value, read as mm, would be inside the travel."""
    match = _TRAVEL_VALUE.match(message)
    if match is None:
        return False
    value, low, high = (float(match.group(i)) for i in (2, 3, 4))
    return abs(value) > 3 * max(abs(low), abs(high)) and low <= value / 25.4 <= high


def _column(line: Line, token: str | None) -> int:
    start = len(line.raw) - len(line.raw[3:].lstrip()) + 1 if len(line.raw) > 3 else 1
    if token == line.raw[:3]:
        return 1
    if token:
        found = line.raw.find(token, 3)
        if found >= 0:
            return found + 1
    return start


def _is_skip_900(line: Line) -> bool:
    return (
        line.statement is not None
        and line.kind is Kind.SKIP
        and int(line.statement.value("target")) == BLOCK_END_LINE
    )


#: Lines that axis-only lines look through to find what they continue.
_TRANSPARENT = frozenset({Kind.AXIS, Kind.COMMENT, Kind.BLANK})


def validate(program: Program, context: ValidationContext | None = None) -> Validation:
    """Check ``program`` completely; see the module docstring."""
    context = context or ValidationContext()
    role = resolve_role(program, context.role)
    checker = _Checker(program, context, role)
    checker.run()
    blocks: list[Block] | None = None
    path: Toolpath | None = None
    if checker.program.lines and not any(
        p.severity is Severity.ERROR and p.code in ("repeat", "skip", "line-order")
        for p in checker.problems
    ):
        blocks, path = checker.simulate()
    problems = sorted(checker.problems, key=lambda p: (p.row, p.column, p.severity.value))
    if program.block_count <= 1:
        # Block numbers only help in multi-block files.
        problems = [p if p.block is None else replace(p, block=None) for p in problems]
    has_errors = any(p.severity is Severity.ERROR for p in problems)
    return Validation(program, role, problems, None if has_errors else blocks, path)
