"""The motion model (no I/O, no clock): how long a control takes to execute each block.

One model for the emulator's execution time, the kind's time estimate and preview, and the
benches' bounds::

    model = MotionModel(rapid_mm_min=10000)
    seconds = block_seconds(gcode.blocks(text), model)    # one figure per block
    machine = Machine(model)                              # block by block (the emulator)
    machine.step(block).seconds

Rapid (G00): each axis at the rapid rate on its own, so the longest axis decides. Feed
(G01/G02/G03): the path length (arcs by their length, helical Z included) at F, mm/min (G94;
G95: F mm/rev times S). Dwell G04: P ms or X s. Canned cycles (G73, G81-G89): rapid to the
hole, feed to Z, rapid back to R. Inch programs (G20) are turned into mm. With
``accel_mm_s2`` set, every move starts and stops at rest (a trapezoid); without it, moves
run at their rate from start to end (a control that looks ahead through short blocks).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from cellctl.kinds.iso_cnc.gcode import ARCS, G_GROUPS, Block

Point = tuple[float, float, float]
_AXES = "XYZ"
_PLANES = {17: (0, 1, "I", "J"), 18: (2, 0, "K", "I"), 19: (1, 2, "J", "K")}


@dataclass(frozen=True)
class MotionModel:
    """A control's motion, as the time figures need it."""

    rapid_mm_min: float = 10000.0
    accel_mm_s2: float | None = None
    block_s: float = 0.0
    """Fixed time each block takes to be read and set up, s (0: none)."""


@dataclass(frozen=True, slots=True)
class Step:
    """One block executed: its seconds and the path it took (points after the start)."""

    line: int
    seconds: float
    kind: str  # "rapid", "feed", "dwell" or "" (no motion)
    start: Point
    points: tuple[Point, ...] = ()


@dataclass
class Machine:
    """The modal state of a control running a program, one block at a time."""

    model: MotionModel = field(default_factory=MotionModel)
    position: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    motion: float = 0.0
    cycle: float | None = None
    feed: float = 0.0
    speed: float = 0.0
    per_rev: bool = False
    absolute: bool = True
    inch: bool = False
    plane: int = 17
    r_plane: float | None = None
    z_depth: float | None = None

    def _move_time(self, length: float, rate_mm_min: float) -> float:
        if length <= 0 or rate_mm_min <= 0:
            return 0.0
        v = rate_mm_min / 60.0
        a = self.model.accel_mm_s2
        if a is None or a <= 0:
            return length / v
        if length >= v * v / a:
            return length / v + v / a
        return 2.0 * math.sqrt(length / a)

    def _feed_rate(self) -> float:
        rate = self.feed * (25.4 if self.inch else 1.0)
        return rate * self.speed if self.per_rev else rate

    def _target(self, block: Block) -> list[float]:
        scale = 25.4 if self.inch else 1.0
        end = list(self.position)
        for i, axis in enumerate(_AXES):
            value = block.get(axis)
            if value is not None:
                end[i] = value * scale if self.absolute else end[i] + value * scale
        return end

    def _rapid(self, start: list[float], end: list[float]) -> float:
        longest = max(abs(e - s) for s, e in zip(start, end, strict=True))
        return self._move_time(longest, self.model.rapid_mm_min)

    def step(self, block: Block) -> Step:
        """Execute ``block``: its time, and the modal state carried to the next one."""
        start: Point = (self.position[0], self.position[1], self.position[2])
        one_shot = None
        for g in block.g_codes:
            group = G_GROUPS.get(g)
            if group == 1:
                self.motion, self.cycle = g, None
            elif group == 9:
                self.cycle = None if g == 80 else g
            elif group == 3:
                self.absolute = g == 90
            elif group == 6:
                self.inch = g == 20
            elif group == 2:
                self.plane = int(g)
            elif group == 5:
                self.per_rev = g == 95
            elif group == 0:
                one_shot = g
        f, s = block.get("F"), block.get("S")
        if f is not None:
            self.feed = f
        if s is not None:
            self.speed = s
        base = self.model.block_s
        if one_shot == 4:
            p, x = block.get("P"), block.get("X")
            dwell = (p / 1000.0) if p is not None else (x or 0.0)
            return Step(block.line, base + dwell, "dwell", start)
        moves = any(block.has(a) for a in _AXES)
        if one_shot == 28 or one_shot == 30:
            mid = self._target(block) if moves else list(self.position)
            home = [0.0, 0.0, 0.0]
            seconds = self._rapid(self.position, mid) + self._rapid(mid, home)
            self.position = home
            return Step(block.line, base + seconds, "rapid", start, (tuple(mid), tuple(home)))  # type: ignore[arg-type]
        if one_shot is not None or not moves:
            if one_shot == 92:
                self.position = self._target(block)
            return Step(block.line, base, "", start)
        if self.cycle is not None:
            return self._cycle(block, start, base)
        end = self._target(block)
        if self.motion == 0:
            seconds = self._rapid(self.position, end)
            self.position = end
            return Step(block.line, base + seconds, "rapid", start, (_pt(end),))
        if self.motion in ARCS:
            points, length = self._arc(block, end)
        else:
            points, length = (_pt(end),), math.dist(self.position, end)
        self.position = end
        seconds = self._move_time(length, self._feed_rate())
        return Step(block.line, base + seconds, "feed", start, points)

    def _cycle(self, block: Block, start: Point, base: float) -> Step:
        scale = 25.4 if self.inch else 1.0
        r, z = block.get("R"), block.get("Z")
        if r is not None:
            self.r_plane = r * scale
        if z is not None:
            self.z_depth = z * scale
        top = self.r_plane if self.r_plane is not None else self.position[2]
        bottom = self.z_depth if self.z_depth is not None else top
        hole = self._target(block)
        hole[2] = top
        seconds = self._rapid(self.position, hole)
        depth = abs(top - bottom)
        seconds += self._move_time(depth, self._feed_rate())
        seconds += self._move_time(depth, self.model.rapid_mm_min)
        self.position = hole
        bottom_point = (hole[0], hole[1], bottom)
        return Step(block.line, base + seconds, "feed", start, (_pt(hole), bottom_point, _pt(hole)))

    def _arc(self, block: Block, end: list[float]) -> tuple[tuple[Point, ...], float]:
        """The arc's points (a few per quarter turn) and its length, helix included."""
        a, b, ia, ib = _PLANES[self.plane]
        c = 3 - a - b
        scale = 25.4 if self.inch else 1.0
        sa, sb, ea, eb = self.position[a], self.position[b], end[a], end[b]
        clockwise = self.motion == 2.0
        r_word = block.get("R")
        if r_word is not None:
            r = abs(r_word * scale)
            chord = math.hypot(ea - sa, eb - sb)
            if chord == 0 or r == 0:
                return (_pt(end),), math.dist(self.position, end)
            h = math.sqrt(max(r * r - chord * chord / 4, 0.0))
            ma, mb = (sa + ea) / 2, (sb + eb) / 2
            ua, ub = (eb - sb) / chord, -(ea - sa) / chord  # the chord's normal, to the right
            side = 1.0 if clockwise == (r_word > 0) else -1.0
            ca, cb = ma + side * h * ua, mb + side * h * ub
        else:
            ca = sa + (block.get(ia) or 0.0) * scale
            cb = sb + (block.get(ib) or 0.0) * scale
        r = math.hypot(sa - ca, sb - cb)
        t0 = math.atan2(sb - cb, sa - ca)
        t1 = math.atan2(eb - cb, ea - ca)
        sweep = (t0 - t1) if clockwise else (t1 - t0)
        sweep %= 2 * math.pi
        if sweep < 1e-12:
            sweep = 2 * math.pi  # start = end: a full circle
        planar = r * sweep
        rise = end[c] - self.position[c]
        length = math.hypot(planar, rise)
        pieces = max(1, min(64, int(sweep / (math.pi / 8)) + 1))
        points: list[Point] = []
        for k in range(1, pieces + 1):
            t = t0 + (-sweep if clockwise else sweep) * k / pieces
            p = [0.0, 0.0, 0.0]
            p[a], p[b] = ca + r * math.cos(t), cb + r * math.sin(t)
            p[c] = self.position[c] + rise * k / pieces
            points.append(_pt(p))
        return tuple(points), length


def _pt(p: list[float]) -> Point:
    return (p[0], p[1], p[2])


def steps(blocks: Iterable[Block], model: MotionModel | None = None) -> list[Step]:
    """Each block executed in order on ``model``."""
    machine = Machine(model or MotionModel())
    return [machine.step(b) for b in blocks]


def block_seconds(blocks: Iterable[Block], model: MotionModel | None = None) -> list[float]:
    """Each block's seconds on ``model`` (the emulator runs the same :class:`Machine`)."""
    machine = Machine(model or MotionModel())
    return [machine.step(b).seconds for b in blocks]


def program_seconds(blocks: Iterable[Block], model: MotionModel | None = None) -> float:
    """The whole program's seconds."""
    return math.fsum(block_seconds(blocks, model))
