"""The iso-cnc kind's options (``[machines.NAME] options``) and what is checked with them
before a byte goes out::

    options = IsoCncOptions(dc3_tolerance=2, cs_flow=True)
    tape = read_program(Path("O1234.nc"), options)   # UsageError: every error, line and column
"""

from __future__ import annotations

import asyncio
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field

from cellctl.errors import UsageError
from cellctl.files import read_file
from cellctl.kinds.iso_cnc import gcode, tape
from cellctl.kinds.iso_cnc.motion import MotionModel

#: The kind's default line: Fanuc's 9600 baud, ISO (7 bits, even parity), 2 stop bits.
ISO_LINE = "9600,7E2"
#: The largest program cellctl reads into a control's memory (a read-in), and its blocks:
#: cellctl's caps, far above any control's memory (Fanuc: 10 m to a few MB of tape).
READ_IN_MAX_BYTES = 16 * 1024 * 1024
READ_IN_MAX_BLOCKS = 500_000
#: The largest program cellctl drip-feeds: a drip-feed streams (the host models the
#: blocks as they go, never all at once), so only the file's own size is held.
DRIP_MAX_BYTES = 1024 * 1024 * 1024


class IsoCncOptions(BaseModel):
    """The control's options (``[machines.NAME] options``); baud, parity and stop bits are
    the machine's ``line`` (default 9600,7E2)."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    code: Literal["ISO"] = "ISO"
    """Tape code: ISO (EIA may come later)."""
    dc3_tolerance: int = Field(default=10, ge=0, le=1000)
    """Characters the control accepts after its DC3 (Fanuc: 10; a CS-only control: 2)."""
    cs_flow: bool = False
    """Obey the control's RTS (CS) too: needs a serial port or rfc2217:// (modem lines)."""
    leader: int = Field(default=20, ge=0, le=10000)
    """NUL characters sent before the tape."""
    trailer: int = Field(default=20, ge=0, le=10000)
    """NUL characters sent after the tape."""
    percent: bool = True
    """Frame the tape with ``%`` (start and end of transmission)."""
    o_digits: int = Field(default=4, ge=1, le=8)
    """Digits of an O-number the control takes (4 on most Fanuc controls, 8 on newer)."""
    buffer_size: int = Field(default=256, ge=16, le=1 << 20)
    """The control's reader buffer, characters (the drip-feed model)."""
    high_water: int | None = Field(default=None, ge=1)
    """Where the control sends DC3 (default: buffer_size - dc3_tolerance)."""
    low_water: int | None = Field(default=None, ge=0)
    """Where it sends DC1 again (default: buffer_size // 2): corrects the model."""
    margin: int = Field(default=24, ge=0, le=1000)
    """Characters kept clear of the high-water mark in the model (its error: a device
    server's jitter, the control's own timing)."""
    link_lag_s: float = Field(default=0.002, ge=0, le=10)
    """Seconds a write may take to reach the line beyond its own line time (a USB adapter's
    1 ms frames, a device server's network): the model counts a block out of the control's
    buffer that much later (a character still held on the way is still to come)."""
    burst: int = Field(default=4, ge=1, le=4096)
    """Characters written at a time (what may be in flight after a DC3, with ``ahead``)."""
    ahead: float = Field(default=2.0, ge=0, le=4096)
    """Characters of line time a burst is written before the last one has crossed."""
    pace_s: float = Field(default=0.002, ge=0, le=1)
    """Line time a burst covers at least, s (the host's own timer granularity): at 9600 baud
    ``burst`` is more; on a line made faster (an emulated cell) bursts grow to keep it busy."""
    store_cps: float = Field(default=0.0, ge=0)
    """Characters/s the control stores during a read-in (0: as fast as the line)."""
    rapid_mm_min: float = Field(default=10000.0, gt=0)
    """The control's rapid traverse, mm/min (the motion model)."""
    accel_mm_s2: float | None = Field(default=None, gt=0)
    """The control's acceleration, mm/s² (None: moves at their rate end to end)."""
    motion_scale: float = Field(default=1.0, gt=0)
    """For an emulated control only (its ``--time-scale``, an emulated cell's scale): it runs
    this many times faster than the motion model, whose block times (a drip-feed's end,
    ``dnc check``'s run time and forecast) are divided by it. Leave it 1 for a real machine.
    Stalls are said in wall seconds whatever it is."""
    arc_tolerance_mm: float = Field(default=0.01, gt=0, le=10)
    """Start and end radius of an arc may differ this much (the G-code check)."""
    dc1_timeout: float = Field(default=120.0, gt=0, le=86400)
    """Seconds to wait for the control's DC1 (the operator presses READ or CYCLE START), by
    ``dnc send`` and ``drip`` and a cell's run; a remote request's answer waits 30 minutes."""
    stop_timeout: float = Field(default=600.0, gt=0, le=86400)
    """Seconds a DC3 may hold the host before it gives up (a long block, a feed hold)."""
    end_margin: float = Field(default=2.0, ge=1, le=100)
    """A drip-feed may take this many times its modelled time ..."""
    end_extra: float = Field(default=60.0, ge=0, le=86400)
    """... plus this many seconds, before the driver gives up on it."""
    ready_wait: float = Field(default=2.0, gt=0, le=600)
    """Seconds the control may take to show ready."""
    setup_timeout: float = Field(default=1800.0, gt=0, le=86400)
    """Seconds a setup program may take."""
    go_pulse: float = Field(default=0.5, gt=0, le=10)
    """Seconds the cycle-start output stays on (a cell's GO) to start a drip-feed."""

    def high_water_mark(self) -> int:
        """Characters in the control's buffer at which it sends DC3."""
        return self.high_water or self.buffer_size - self.dc3_tolerance

    def sender(self, char_time: float) -> tuple[int, int]:
        """How the host writes at ``char_time`` s a character: (characters a burst, most
        characters it keeps in the control's buffer by its model)."""
        burst = max(self.burst, math.ceil(self.pace_s / char_time))
        return burst, max(burst, self.high_water_mark() - self.margin)

    def check_options(self, *, drip: bool = True) -> gcode.CheckOptions:
        """The G-code check's options; cellctl's caps of a drip-feed (``drip``, the widest:
        1 GiB, any number of blocks) or of a read-in into memory (16 MiB, 500,000 blocks)."""
        if drip:
            return gcode.CheckOptions(
                o_digits=self.o_digits,
                arc_tolerance_mm=self.arc_tolerance_mm,
                max_bytes=DRIP_MAX_BYTES,
                max_blocks=DRIP_MAX_BYTES,
            )
        return gcode.CheckOptions(
            o_digits=self.o_digits,
            arc_tolerance_mm=self.arc_tolerance_mm,
            max_bytes=READ_IN_MAX_BYTES,
            max_blocks=READ_IN_MAX_BLOCKS,
            limit_note=" for a read-in into a control's memory (cellctl's cap, not the "
            "control's): drip-feed it (`cellctl dnc drip`, up to 1 GiB)",
        )

    def motion(self) -> MotionModel:
        return MotionModel(rapid_mm_min=self.rapid_mm_min, accel_mm_s2=self.accel_mm_s2)


def program_text(data: bytes, name: str = "program") -> str:
    """A program file's bytes as text; UsageError at the line of a byte ISO code has not."""
    try:
        return data.decode("ascii")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise UsageError(f"{name}:{line}: byte 0x{data[e.start]:02X} is not ISO code") from None


def prepare(
    data: bytes, options: IsoCncOptions, name: str = "program", drip: bool = False
) -> bytes:
    """A program file's bytes as the tape that goes on the line; UsageError (every error of
    the G-code check, with line and column) before a byte goes out. ``drip``: checked with
    a drip-feed's caps (:meth:`IsoCncOptions.check_options`), else a read-in's."""
    text = program_text(data, name)
    found = gcode.errors(text, options.check_options(drip=drip))
    if found:
        shown = [f.format(name) for f in found[:5]]
        more = f" (and {len(found) - 5} more)" if len(found) > 5 else ""
        raise UsageError("; ".join(shown) + more)
    return tape.frame(text, leader=options.leader, trailer=options.trailer, percent=options.percent)


T = TypeVar("T")

#: A program longer than this is checked and modelled in a thread, off the event loop: a
#: 5 MB file takes seconds of G-code check, and a server's other machines' drip-feeds must
#: be answered meanwhile (their buffers run dry in less).
OFF_LOOP_BYTES = 64 * 1024


async def off_loop(data: bytes, fn: Callable[..., T], *args: Any) -> T:
    """``fn(*args)`` (a check or a model of the program ``data``), in a thread when ``data``
    is longer than :data:`OFF_LOOP_BYTES`::

        framed = await off_loop(data, prepare, data, options, "O1234.nc")
    """
    if len(data) > OFF_LOOP_BYTES:
        return await asyncio.to_thread(fn, *args)
    return fn(*args)


def read_capped(path: Path, cap: int) -> bytes:
    """:func:`~cellctl.files.read_file` of a program, at most ``cap`` bytes (OSError EFBIG
    over it), reading no more than the file holds: a cap of a GiB never asks for a GiB of
    memory up front (a read asks for its whole limit at once)."""
    try:
        size = os.stat(path).st_size
    except OSError:
        size = cap  # read_file says why, in its words
    return read_file(path, limit=min(cap, size + 65536))


def read_program(path: Path, options: IsoCncOptions) -> bytes:
    """:func:`prepare` for a drip-feed of a file (UsageError if it cannot be read)."""
    try:
        data = read_capped(path, DRIP_MAX_BYTES)
    except OSError as e:
        raise UsageError(f"{path}: cannot read: {e.strerror or e}") from None
    return prepare(data, options, path.name, drip=True)  # a cell's program is drip-fed
