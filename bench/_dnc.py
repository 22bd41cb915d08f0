"""What the DNC benches share: the 3-D surfacing program and the ideal host's bound.

The program (:func:`surfacing_program`): a raster over a wavy surface, 1 mm segments, in
bands of rows at two feeds. At ``fast_feed`` a block runs quicker than the line brings it
(the line is the limit and the control waits for data: the stall a host cannot avoid); at
``slow_feed`` slower (the buffer fills, DC3 / DC1 cycle).

The bound (:func:`ideal_drip`): an ideal host on the same tape, the same line rate and the
control's own motion model (``cellctl.kinds.iso_cnc.motion``, which the emulator runs): it
sends at the line rate from the control's DC1 until its DC3, and hears each at once (no
character after a DC3, none lost before a DC1). The control takes a block out of its buffer
when it starts it (once its LF is in), runs it for the model's time, DC3 at ``high_water``
characters, DC1 at ``low_water`` -- the emulator's rules. Computed, not run.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass

from cellctl.kinds.iso_cnc.emulator import IsoCncEmulator
from cellctl.kinds.iso_cnc.gcode import PROGRAM_ENDS, parse_block
from cellctl.kinds.iso_cnc.motion import Machine, MotionModel


def surfacing_program(
    size: int,
    *,
    number: int = 2000,
    fast_feed: float = 6000.0,
    slow_feed: float = 1500.0,
    bands: int = 6,
    row_mm: int = 200,
) -> str:
    """A surfacing program of about ``size`` characters (see module docstring)."""
    head = [
        f"O{number:04d} (SURFACE {size} CHARS)",
        "G21 G90 G17 G94",
        "G00 Z5.",
        "G00 X0 Y0",
        f"G01 Z0 F{fast_feed:.0f}",
    ]
    body: list[str] = []
    used = sum(len(x) + 1 for x in head) + 4
    rows = 0
    approx_row = 15 * row_mm
    total_rows = max(2, size // approx_row)
    per_band = max(1, math.ceil(total_rows / bands))
    while used < size - 20:
        band = rows // per_band
        feed = fast_feed if band % 2 == 0 else slow_feed
        y = rows * 0.5
        line = f"Y{y:.1f} F{feed:.0f}"
        body.append(line)
        used += len(line) + 1
        xs = range(1, row_mm + 1) if rows % 2 == 0 else range(row_mm - 1, -1, -1)
        for x in xs:
            z = 2.0 * math.sin(x / 15.0) * math.cos(y / 10.0)
            line = f"X{x}. Z{z:.3f}"
            body.append(line)
            used += len(line) + 1
            if used >= size - 20:
                break
        rows += 1
    tail = ["G00 Z5.", "M30"]
    return "\n".join(head + body + tail) + "\n"


@dataclass(frozen=True)
class Bound:
    """The ideal host's drip-feed: total seconds, stall seconds, blocks run."""

    total_s: float
    stall_s: float
    blocks: int
    machine_s: float


def _segments(tape: bytes, model: MotionModel) -> list[tuple[int, float, bool]]:
    """The tape as the control takes it: (end index, seconds, a block) per LF-ended piece,
    to the block that ends the program."""
    out: list[tuple[int, float, bool]] = []
    machine = Machine(model)
    start = 0
    started = False
    count = 0
    while True:
        i = tape.find(b"\n", start)
        if i < 0:
            break
        raw = tape[start : i + 1]
        text = raw.replace(b"\x00", b"").replace(b"\r", b"").decode("latin-1")
        start = i + 1
        if "%" in text:
            if started:
                break
            started = True
            out.append((start, 0.0, False))
            continue
        started = True
        block = parse_block(count + 1, text.rstrip("\n"), [])
        if not block.words:
            out.append((start, 0.0, False))
            continue
        count += 1
        out.append((start, machine.step(block).seconds, True))
        if PROGRAM_ENDS & set(block.m_codes):
            break
    return out


def ideal_drip(
    tape: bytes, chars_per_s: float, model: MotionModel, *, high_water: int, low_water: int
) -> Bound:
    """The ideal host's drip-feed of ``tape`` (see module docstring), in the control's time."""
    char_s = 1.0 / chars_per_s
    segments = _segments(tape, model)
    n = segments[-1][0] if segments else 0
    ready = [math.inf] * len(segments)  # when each segment's LF is in
    sent = 0  # characters arrived
    line_free = 0.0  # when the next character may start
    buffered = 0
    stopped = False
    j = 0  # next segment to take
    free = 0.0  # when the machine is done with what it took
    stall = 0.0
    machine_s = 0.0
    blocks = 0
    r = 0  # next segment whose LF is not in yet
    while j < len(segments):
        arrive = line_free + char_s if (sent < n and not stopped) else math.inf
        take = max(free, ready[j])
        if take <= arrive and take < math.inf:
            end, seconds, is_block = segments[j]
            length = end - (segments[j - 1][0] if j else 0)
            if blocks and ready[j] > free:
                stall += ready[j] - free
            buffered -= length
            free = take + seconds
            machine_s += seconds
            blocks += int(is_block)
            j += 1
            if stopped and buffered <= low_water:
                stopped = False
                line_free = max(line_free, take)  # DC1 heard at once
            continue
        sent += 1
        buffered += 1
        line_free = arrive
        while r < len(segments) and segments[r][0] <= sent:  # its LF is in
            ready[r] = arrive
            r += 1
        if buffered >= high_water:
            stopped = True  # DC3 heard at once: not one character more
    return Bound(total_s=free, stall_s=stall, blocks=blocks, machine_s=machine_s)


class TimedControl(IsoCncEmulator):
    """The emulated control, noting (loop time) when each read began and ended."""

    began: float = math.nan
    ended: float = math.nan

    def _begin_read(self) -> None:
        self.began = asyncio.get_running_loop().time()
        super()._begin_read()

    def _finish_read(self) -> None:
        self.ended = asyncio.get_running_loop().time()
        super()._finish_read()
