"""What the iso-cnc driver reports about a transfer (no I/O)::

report = await cnc.read_in(data, progress=lambda p: print(p.chars_sent, p.phase))
report.ended_early          # True when :meth:`IsoCncDriver.end_tape` cut the tape short
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass


@dataclass
class TransferProgress:
    """Where a transfer stands (passed to ``progress`` as it goes)."""

    chars_sent: int
    chars_total: int
    chars_per_s: float
    buffer_stops: int
    elapsed_s: float
    eta_s: float
    phase: str  # "waiting" (for DC1), "sending", "stopped" (DC3), "running", "receiving", "done"


@dataclass
class TransferReport:
    """A finished transfer: its totals, and the alarm if the control raised one."""

    chars_sent: int
    chars_total: int
    chars_per_s: float
    buffer_stops: int
    elapsed_s: float
    alarm: int | None = None
    stalls_modelled_s: float = 0.0
    ended_early: bool = False
    """The tape was ended before its last block (the rest of a block, then ``%``)."""


Progress = Callable[[TransferProgress], None]
