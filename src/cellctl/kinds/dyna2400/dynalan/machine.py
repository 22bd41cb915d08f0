"""What DYNALAN statements do: the machine model shared by the toolpath, the validator and the
mill emulator.

Usage::

    state = MachineState.initial(Units.INS)
    for step in run_block(memory, state, MachineConfig()):   # memory: {number: Statement}
        for move in step.moves: ...                          # motion in reference coordinates
        if step.operator: ...                                # SETUP: wait for the operator
        if step.outcome: ...                                 # BLOCK_END, HALT or END

:func:`run_block` follows the controller's flow (SKIP TO, REPEAT, the ``900`` line) over
numbered memory, so the emulator can run it over its 1000-line memory, stale lines included. A
statement the controller cannot execute raises :class:`ProgramFault` when it is reached, as the
real controller only finds out then. The data types (:class:`MachineState`, :class:`Move`,
:class:`Step` ...) live in :mod:`cellctl.kinds.dyna2400.dynalan.state` and are re-exported here.

Times: each move takes the longest of its axes' times (each axis runs at most at its feed rate;
rapid moves at the configured rapid rate); arcs take their length at the XY feed rate.

Cost: a statement's motion is counted before it is made. A canned cycle or a drill hole that
would make more than :data:`~cellctl.kinds.dyna2400.dynalan.table.PASSES_MAX` passes (rings, rows,
pecks) or more than :data:`~cellctl.kinds.dyna2400.dynalan.table.STATEMENT_POINTS_MAX` points is a
:class:`ProgramFault`, as is a value whose arithmetic cannot end (a feed rate, tool diameter,
pass depth or peck of 0 or below), so no program costs more than its size allows.
"""

from __future__ import annotations

import functools
import math
from bisect import bisect_right
from collections.abc import Iterator, Mapping

from cellctl.kinds.dyna2400.dynalan.model import Statement
from cellctl.kinds.dyna2400.dynalan.state import (
    Entry,
    MachineConfig,
    MachineState,
    Move,
    MoveKind,
    Outcome,
    ProgramFault,
    Step,
    Vec,
)
from cellctl.kinds.dyna2400.dynalan.table import (
    ARC_MAX_DEGREES,
    AXES,
    BLOCK_END_LINE,
    CYCLE_KINDS,
    MOTION_KINDS,
    PASSES_MAX,
    RUNAWAY_STEPS,
    STATEMENT_POINTS_MAX,
    Kind,
    Travel,
    Units,
    scale,
)

# The data types live in .state: re-exported, as users import them from here.
__all__ = [
    "ARC_STEP_DEGREES",
    "Entry",
    "MachineConfig",
    "MachineState",
    "Move",
    "MoveKind",
    "Outcome",
    "ProgramFault",
    "Step",
    "Vec",
    "checked_execute",
    "execute",
    "run_block",
    "travel_fault",
]

ARC_STEP_DEGREES = 5.0  # arcs are drawn and checked as chords of at most this angle


def _usable_rate(rate: float, axis: str) -> float:
    """``rate`` when a move can be timed with it; a fault for 0, a negative rate or NaN."""
    if not (rate > 0 and math.isfinite(rate)):
        raise ProgramFault("feed", f"feed rate {rate:g} for {axis}: a move needs a rate above 0")
    return rate


def _positive(value: float, what: str, code: str = "range") -> float:
    """``value`` when it is above 0 and finite; a fault naming ``what`` otherwise."""
    if not (value > 0 and math.isfinite(value)):
        raise ProgramFault(code, f"{what} {value:g}: must be above 0")
    return value


def _count(what: str, total: float, step: float, *, unit: str = "passes") -> int:
    """How many steps of ``step`` cover ``total``, refused beyond :data:`PASSES_MAX`."""
    ratio = total / step if total > 0 else 1.0
    if not ratio <= PASSES_MAX:  # NaN and inf included
        many = f"{math.ceil(ratio - 1e-6):,}" if math.isfinite(ratio) else "endless"
        raise ProgramFault("cycle", f"{what} {step:g} gives {many} {unit}; at most {PASSES_MAX:,}")
    return max(1, math.ceil(ratio - 1e-9))


def _check_points(name: str, points: int) -> None:
    if points > STATEMENT_POINTS_MAX:
        raise ProgramFault(
            "cycle",
            f"{name} makes {points:,} points of motion; at most {STATEMENT_POINTS_MAX:,} "
            "(a larger DP=, TD= or fewer passes)",
        )


class _Motion:
    """Builds moves from the current position, keeping ``state.position`` up to date."""

    def __init__(self, state: MachineState, config: MachineConfig, number: int) -> None:
        self.state = state
        self.number = number
        self.rapid = scale(_usable_rate(config.rapid_rate, "rapid moves"), state.units)
        self.moves: list[Move] = []

    def _axis_seconds(self, a: Vec, b: Vec, rates: Mapping[str, float]) -> float:
        seconds = 0.0
        for i, ax in enumerate(AXES):
            distance = abs(b[i] - a[i])
            if distance > 0:
                seconds = max(seconds, distance / _usable_rate(rates[ax], ax))
        return seconds * 60.0

    def to(self, target: Vec, *, rapid: bool = False) -> None:
        start = self.state.position
        if math.dist(start, target) < 1e-12:
            return
        if rapid:
            seconds = self._axis_seconds(start, target, dict.fromkeys(AXES, self.rapid))
            rate = self.rapid
        else:
            seconds = self._axis_seconds(start, target, self.state.feed)
            moving = [ax for i, ax in enumerate(AXES) if abs(target[i] - start[i]) > 1e-12]
            rate = min(self.state.feed[ax] for ax in moving)
        kind = MoveKind.RAPID if rapid else MoveKind.FEED
        self.moves.append(Move(kind, (start, target), rate, seconds, self.number))
        self.state.position = target

    def to_xy(self, x: float, y: float, *, rapid: bool = False) -> None:
        self.to((x, y, self.state.position[2]), rapid=rapid)

    def to_z(self, z: float, *, rapid: bool = False) -> None:
        p = self.state.position
        self.to((p[0], p[1], z), rapid=rapid)

    def arc(self, cx: float, cy: float, degrees: float) -> None:
        x, y, z = self.state.position
        radius = math.hypot(x - cx, y - cy)
        if radius < 1e-9:
            raise ProgramFault("arc", "arc of radius 0: the tool is at the arc's centre")
        a0 = math.atan2(y - cy, x - cx)
        steps = max(2, math.ceil(abs(degrees) / ARC_STEP_DEGREES))
        path = [(x, y, z)]
        for i in range(1, steps + 1):
            a = a0 + math.radians(degrees) * i / steps
            path.append((cx + radius * math.cos(a), cy + radius * math.sin(a), z))
        rate = min(_usable_rate(self.state.feed["X"], "X"), _usable_rate(self.state.feed["Y"], "Y"))
        length = radius * math.radians(abs(degrees))
        seconds = length / rate * 60.0
        self.moves.append(Move(MoveKind.FEED, tuple(path), rate, seconds, self.number))
        self.state.position = path[-1]

    def dwell(self, seconds: float) -> None:
        p = self.state.position
        self.moves.append(Move(MoveKind.DWELL, (p, p), 0.0, seconds, self.number))


def _levels(top: float, bottom: float, per_pass: float | None) -> list[float]:
    if not bottom < top - 1e-12:
        raise ProgramFault("cycle", f"ZD= {bottom:g} is not below the start Z {top:g}")
    if per_pass is None:
        return [bottom]
    _positive(per_pass, "DP= (depth a pass)", "cycle")
    _count("pass depth", top - bottom, per_pass)
    levels = []
    z = top
    while z - per_pass > bottom + 1e-9:
        z -= per_pass
        levels.append(z)
    levels.append(bottom)
    return levels


def _cycle(stmt: Statement, state: MachineState, config: MachineConfig, m: _Motion) -> None:
    """Expand a canned cycle (the project's syntax) into moves; it ends where it started."""
    x0, y0, z0 = state.position
    fx, fy, fz = state.frame()
    bottom = stmt.value("ZD") + fz
    levels = _levels(z0, bottom, stmt.values.get("DP"))
    radius = _positive(state.tool_diameter, "tool diameter (TD)") / 2
    kind = stmt.kind
    passes = len(levels)
    if kind is Kind.MILL:
        _check_points(kind.value, passes * 2)
        ends = [(x0, y0), (stmt.value("X") + fx, stmt.value("Y") + fy)]
        for i, z in enumerate(levels):
            m.to_z(z)
            m.to_xy(*ends[(i + 1) % 2])
    elif kind in (Kind.FRAME, Kind.RFRAME):
        xs = sorted((x0, x0 + stmt.value("XL")))
        ys = sorted((y0, y0 + stmt.value("YL")))
        if kind is Kind.RFRAME:
            xs, ys = [xs[0] - radius, xs[1] + radius], [ys[0] - radius, ys[1] + radius]
        corners = [(xs[0], ys[0]), (xs[1], ys[0]), (xs[1], ys[1]), (xs[0], ys[1]), (xs[0], ys[0])]
        _check_points(kind.value, passes * 5)
        m.to_xy(*corners[0], rapid=True)
        for z in levels:
            m.to_z(z)
            for corner in corners[1:]:
                m.to_xy(*corner)
    elif kind is Kind.RPOCKET:
        xs = sorted((x0, x0 + stmt.value("XL")))
        ys = sorted((y0, y0 + stmt.value("YL")))
        if xs[1] - xs[0] <= 2 * radius or ys[1] - ys[0] <= 2 * radius:
            raise ProgramFault("cycle", "RPOCKET is not wider than the tool (TD)")
        lo_x, hi_x, lo_y, hi_y = xs[0] + radius, xs[1] - radius, ys[0] + radius, ys[1] - radius
        step = _positive(config.step_over, "step over") * state.tool_diameter
        rows = _count("step over", hi_y - lo_y, step, unit="rows")
        _check_points(kind.value, passes * (2 * rows + 10))
        m.to_xy(lo_x, lo_y, rapid=True)
        for z in levels:
            m.to_z(z)
            for r in range(rows + 1):
                y = lo_y + (hi_y - lo_y) * r / rows
                m.to_xy(m.state.position[0], y)
                m.to_xy(hi_x if r % 2 == 0 else lo_x, y)
            for corner in ((lo_x, hi_y), (lo_x, lo_y), (hi_x, lo_y), (hi_x, hi_y), (lo_x, hi_y)):
                m.to_xy(*corner)
            m.to_z(z0, rapid=True)
            m.to_xy(lo_x, lo_y, rapid=True)
    elif kind is Kind.CPOCKET:
        outer = stmt.value("R") - radius
        if outer <= 0:
            raise ProgramFault("cycle", "CPOCKET radius is not larger than the tool radius")
        step = _positive(config.step_over, "step over") * state.tool_diameter
        rings = _count("step over", outer, step, unit="rings")
        arc_points = 2 * math.ceil(180.0 / ARC_STEP_DEGREES)
        _check_points(kind.value, passes * (rings * (arc_points + 1) + 3))
        for z in levels:
            m.to_xy(x0, y0, rapid=True)
            m.to_z(z)
            for r in range(1, rings + 1):
                m.to_xy(x0 + outer * r / rings, y0)
                m.arc(x0, y0, 180.0)
                m.arc(x0, y0, 180.0)
            m.to_z(z0, rapid=True)
    elif kind is Kind.ARCFRAME:
        sweep = stmt.value("A")
        if abs(sweep) > 360.0:
            raise ProgramFault("cycle", f"ARCFRAME sweeps {sweep:g} degrees: at most 360")
        arc_radius = stmt.value("R")
        if arc_radius <= 0:
            raise ProgramFault("cycle", "ARCFRAME needs R= above 0")
        a = math.radians(stmt.values.get("AS", 0.0))
        _check_points(kind.value, passes * (math.ceil(abs(sweep) / ARC_STEP_DEGREES) + 3))
        m.to_xy(x0 + arc_radius * math.cos(a), y0 + arc_radius * math.sin(a), rapid=True)
        for i, z in enumerate(levels):
            m.to_z(z)
            m.arc(x0, y0, sweep if i % 2 == 0 else -sweep)
    m.to_z(z0, rapid=True)
    m.to_xy(x0, y0, rapid=True)


def _drill_hole(state: MachineState, m: _Motion, x: float, y: float) -> None:
    top, bottom, peck = state.drill_top, state.drill_bottom, state.drill_peck
    if top is None or bottom is None:
        raise ProgramFault("drill", "drill hole before ZH= and ZD= are set")
    fz = state.frame()[2]
    top, bottom = top + fz, bottom + fz
    if bottom >= top:
        raise ProgramFault("drill", "ZD= must be below ZH=")
    if peck is not None and peck < 0:
        raise ProgramFault("drill", f"PECK= {peck:g}: 0 (one plunge) or a positive depth")
    if peck:
        pecks = _count("peck", top - bottom, peck, unit="pecks")
        _check_points("drill hole", pecks * 3)
    m.to_z(top, rapid=True)
    m.to_xy(x, y, rapid=True)
    depth = top
    while depth > bottom + 1e-9:
        depth = max(depth - peck, bottom) if peck and peck > 0 else bottom
        m.to_z(depth)
        m.to_z(top, rapid=True)
        if depth > bottom + 1e-9:
            m.to_z(depth, rapid=True)


def execute(
    stmt: Statement, state: MachineState, config: MachineConfig, number: int = 0
) -> list[Move]:
    """Apply one statement to ``state`` and return its moves (flow statements do nothing here).

    Raises :class:`ProgramFault` for what the controller cannot do (an arc over 180 degrees, an
    axis-only line out of context ...). Travel is checked by :func:`travel_fault`.
    """
    m = _Motion(state, config, number)
    kind = stmt.kind
    context = state.axis_context
    if kind not in (Kind.AXIS, Kind.COMMENT, Kind.BLANK):
        state.axis_context = None
    try:
        if kind is Kind.START:
            state.set_units(Units(stmt.text["units"]))
        elif kind is Kind.SETUP:
            # The operator jogs to the reference zero: the tool is there afterwards.
            state.position = (0.0, 0.0, 0.0)
            state.local = False
        elif kind is Kind.TOOL:
            state.tool = int(stmt.value("tool"))
        elif kind is Kind.TD:
            state.tool_diameter = _positive(stmt.value("diameter"), "tool diameter (TD)")
        elif kind is Kind.FEED:
            rate = stmt.value("rate")
            for axis in stmt.text["axes"]:
                state.feed[axis] = _usable_rate(rate, axis)
        elif kind in (Kind.GO, Kind.GR, Kind.GO_FAST, Kind.GR_FAST):
            if len(stmt.words) != 1:
                raise ProgramFault("axis-words", f"{kind.value} takes one axis word a line")
            _axis_move(kind, stmt.words[0], state, m)
            state.axis_context = kind
        elif kind is Kind.AXIS:
            _axis_line(context, stmt, state, m)
        elif kind is Kind.ARC:
            degrees = stmt.value("degrees")
            if abs(degrees) > ARC_MAX_DEGREES + 1e-9:
                raise ProgramFault(
                    "arc", f"arc of {degrees:g} degrees: at most {ARC_MAX_DEGREES:g} a move"
                )
            cx, cy, _ = state.frame()
            m.arc(cx, cy, degrees)
            state.axis_context = Kind.GR
        elif kind is Kind.CLEARANCE:
            m.to_z(scale(config.clearance_z, state.units), rapid=True)
        elif kind is Kind.ZERO_AT:
            state.local_zero = (0.0, 0.0, 0.0)
            state.local = True
            state.axis_context = Kind.ZERO_AT
        elif kind is Kind.REF_COORD:
            state.local = False
        elif kind is Kind.SPINDLE_ON:
            state.spindle_on = True
        elif kind is Kind.SPINDLE_OFF:
            state.spindle_on = False
        elif kind is Kind.SPINDLE_SPEED:
            state.spindle_rpm = int(stmt.value("rpm"))
        elif kind is Kind.COOLANT_ON:
            state.coolant_on = True
        elif kind is Kind.COOLANT_OFF:
            state.coolant_on = False
        elif kind is Kind.DWELL:
            seconds = stmt.value("seconds")
            if not (seconds >= 0 and math.isfinite(seconds)):
                raise ProgramFault("range", f"DWELL {seconds:g}: a time of 0 seconds or more")
            m.dwell(seconds)
        elif kind is Kind.DRILL:
            peck = stmt.value("peck")
            if not (peck >= 0 and math.isfinite(peck)):
                raise ProgramFault("drill", f"PECK= {peck:g}: 0 (one plunge) or a positive depth")
            state.drill_peck = peck
        elif kind is Kind.DRILL_TOP:
            state.drill_top = stmt.value("z")
        elif kind is Kind.DRILL_BOTTOM:
            state.drill_bottom = stmt.value("z")
            state.axis_context = Kind.DRILL_BOTTOM
        elif kind in CYCLE_KINDS:
            _cycle(stmt, state, config, m)
    except ProgramFault as fault:
        raise ProgramFault(fault.code, fault.message, number) from None
    return m.moves


def _axis_move(kind: Kind, word: tuple[str, float], state: MachineState, m: _Motion) -> None:
    axis, value = word
    i = AXES.index(axis)
    target = list(state.position)
    if kind in (Kind.GO, Kind.GO_FAST):
        target[i] = value + state.frame()[i]
    else:
        target[i] += value
    m.to((target[0], target[1], target[2]), rapid=kind in (Kind.GO_FAST, Kind.GR_FAST))


def _axis_line(context: Kind | None, stmt: Statement, state: MachineState, m: _Motion) -> None:
    if context in MOTION_KINDS:
        assert context is not None
        if len(stmt.words) != 1:
            raise ProgramFault("continuation", "a continuation line carries one axis word")
        _axis_move(context, stmt.words[0], state, m)
    elif context is Kind.ZERO_AT:
        zero = list(state.local_zero)
        for axis, value in stmt.words:
            zero[AXES.index(axis)] = value
        state.local_zero = (zero[0], zero[1], zero[2])
    elif context is Kind.DRILL_BOTTOM:
        fx, fy, _ = state.frame()
        x, y = state.position[0], state.position[1]
        for axis, value in stmt.words:
            if axis == "Z":
                raise ProgramFault("drill", "hole lines give X and Y only")
            if axis == "X":
                x = value + fx
            else:
                y = value + fy
        _drill_hole(state, m, x, y)
    else:
        raise ProgramFault(
            "context", "axis-only line without a GO/GR, ZERO AT or ZD= line before it"
        )
    state.axis_context = context


@functools.lru_cache(maxsize=16)
def _limits(travel: Travel, units: Units) -> tuple[tuple[float, float], ...]:
    return tuple(travel.limits(axis, units) for axis in AXES)


def travel_fault(moves: list[Move] | tuple[Move, ...], units: Units, travel: Travel) -> str | None:
    """The first point of ``moves`` outside ``travel``, described; None when all are inside."""
    if not moves:
        return None
    # The limits once, not per point nor per statement: a block's path may hold thousands
    # of points, a program hundreds of thousands of statements, and the emulator checks
    # every block it runs.
    limits = _limits(travel, units)
    (x0, x1), (y0, y1), (z0, z1) = ((low - 1e-9, high + 1e-9) for low, high in limits)
    for move in moves:
        for point in move.path:
            x, y, z = point
            if x0 <= x <= x1 and y0 <= y <= y1 and z0 <= z <= z1:
                continue
            for i, axis in enumerate(AXES):
                low, high = limits[i]
                if not low - 1e-9 <= point[i] <= high + 1e-9:
                    return (
                        f"{axis} {point[i]:.4f} is outside the {axis} travel "
                        f"{low:.3f} to {high:.3f} {units.length_name}"
                    )
    return None


def checked_execute(
    stmt: Statement, state: MachineState, config: MachineConfig, number: int = 0
) -> list[Move]:
    """:func:`execute` with the travel checked: a move that would leave the travel raises
    :class:`ProgramFault` and leaves the axes where they were (the controller checks a move
    before it makes it: after the error the machine is not at the point it refused)."""
    before = state.position
    moves = execute(stmt, state, config, number)
    fault = travel_fault(moves, state.units, config.travel)
    if fault:
        state.position = before
        raise ProgramFault("travel", fault, number)
    return moves


def run_block(
    memory: Mapping[int, Entry],
    state: MachineState,
    config: MachineConfig,
    *,
    start: int | None = None,
    check_travel: bool = True,
    skip_malformed: bool = False,
    max_steps: int = RUNAWAY_STEPS,
) -> Iterator[Step]:
    """Execute numbered ``memory`` from ``start`` (its lowest line by default), one step a line.

    Follows SKIP TO, REPEAT / REPEAT END and stops at the blank ``900`` line, HALT or END (the
    last step says which in ``outcome``). Raises :class:`ProgramFault` at a line that cannot run:
    malformed text (unless ``skip_malformed``), a SKIP TO to a missing line, a move outside the
    travel (with ``check_travel``), a loop that never ends (more than ``max_steps`` lines run).
    """
    numbers = sorted(memory)
    if not numbers:
        return
    position = {number: i for i, number in enumerate(numbers)}
    index = 0 if start is None else bisect_right(numbers, start - 1)
    repeats: list[tuple[int, int]] = []  # (index of the first body line, passes left)
    steps = 0
    while index < len(numbers):
        steps += 1
        if steps > max_steps:
            raise ProgramFault(
                "runaway",
                f"the block runs more than {max_steps:,} lines (a loop, or REPEATs nested deep)",
                numbers[index],
            )
        number = numbers[index]
        entry = memory[number]
        if isinstance(entry, str):
            if skip_malformed:
                index += 1
                continue
            raise ProgramFault("malformed", f"cannot execute: {entry}", number)
        kind = entry.kind
        if number == BLOCK_END_LINE and kind is Kind.BLANK:
            yield Step(number, entry, outcome=Outcome.BLOCK_END)
            return
        if kind is Kind.SKIP:
            target = int(entry.value("target"))
            if target not in memory:
                raise ProgramFault("skip-target", f"SKIP TO {target:03d}: no such line", number)
            yield Step(number, entry)
            index = position[target]
            continue
        if kind is Kind.REPEAT:
            repeats.append((index + 1, int(entry.value("count"))))
            yield Step(number, entry)
            index += 1
            continue
        if kind is Kind.REPEAT_END:
            if not repeats:
                raise ProgramFault("repeat", "REPEAT END without REPEAT", number)
            body, left = repeats.pop()
            yield Step(number, entry)
            if left > 1:
                repeats.append((body, left - 1))
                index = body
            else:
                index += 1
            continue
        if kind in (Kind.HALT, Kind.END):
            yield Step(number, entry, outcome=Outcome.HALT if kind is Kind.HALT else Outcome.END)
            return
        if check_travel:
            moves = checked_execute(entry, state, config, number)
        else:
            moves = execute(entry, state, config, number)
        yield Step(number, entry, tuple(moves), operator=kind is Kind.SETUP)
        index += 1
    yield Step(numbers[-1], Statement(Kind.BLANK), outcome=Outcome.BLOCK_END)
