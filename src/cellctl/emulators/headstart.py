"""A mill emulator's head start: motion already done before it was started (a plan that
takes up a running cell's cut mid-way).

A mill kind's emulator mixes :class:`HeadStart` in and passes each move's machine time
through :meth:`HeadStart.skip_done`; the emulated cell sets :attr:`HeadStart.head_start_s`
as the taken-up part's first run starts (``EmulatedCell.place(..., done_s=...)``)::

    class MyMillEmulator(EmulatedDevice, HeadStart):
        ...
        seconds = self.skip_done(move_seconds)   # 0 while the credit lasts
"""

from __future__ import annotations


class HeadStart:
    """The credit of machine seconds of motion still to skip (see module docstring)."""

    #: Machine seconds of motion still to skip: each move takes that much less until spent.
    head_start_s: float = 0.0

    def skip_done(self, machine_s: float) -> float:
        """``machine_s`` of motion less what is left of :attr:`head_start_s` (spent so)."""
        skipped = min(machine_s, self.head_start_s)
        if skipped <= 0:
            return machine_s
        self.head_start_s -= skipped
        return machine_s - skipped
