"""The control's reader buffer as the driver models it (see the driver's docstring, point 2)
and what the control does at each LF of a tape. No I/O: times are passed in."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from cellctl.kinds.iso_cnc import gcode
from cellctl.kinds.iso_cnc.motion import Machine, MotionModel


@dataclass
class BufferModel:
    """The control's reader buffer as the host models it (see module docstring, point 2)."""

    drip: bool
    store_cps: float = 0.0
    #: blocks not yet written whole: (offset after its LF, seconds it runs), tape order
    unsent: deque[tuple[int, float]] = field(default_factory=deque)
    #: blocks written whole, not yet started: (when its LF is through, offset, seconds)
    waiting: deque[tuple[float, int, float]] = field(default_factory=deque)
    consumed: int = 0
    free_at: float = 0.0
    started: bool = False
    offset: int = 0
    idle_s: float = 0.0  # modelled stalls: the axes waiting for a block

    def wrote(self, upto: int, through_at: float) -> None:
        """Characters up to offset ``upto`` are written; they are through by ``through_at``."""
        if not self.started and not self.drip:
            self.started, self.free_at = True, through_at
        while self.unsent and self.unsent[0][0] <= upto:
            end, seconds = self.unsent.popleft()
            self.waiting.append((through_at, end, seconds))

    def level(self, sent: int, now: float) -> int:
        """Characters in the control's buffer or on their way to it at ``now``."""
        if not self.drip:
            if self.store_cps <= 0 or not self.started:
                return self.offset
            stored = (now - self.free_at) * self.store_cps
            return max(0, sent - int(stored)) + self.offset
        while self.waiting:
            arrived, end, seconds = self.waiting[0]
            start = max(arrived, self.free_at) if self.started else arrived
            if start > now:
                break
            if self.started and seconds and arrived > self.free_at:
                self.idle_s += arrived - self.free_at
            self.waiting.popleft()
            self.consumed = end
            self.free_at = start + seconds
            self.started = self.started or seconds > 0
        return max(0, sent - self.consumed + self.offset)

    def next_drain(self) -> float | None:
        """When the modelled buffer next loses a block (None: nothing to wait for)."""
        if not self.drip:
            return None
        if not self.waiting:
            return None
        arrived = self.waiting[0][0]
        return max(arrived, self.free_at) if self.started else arrived

    def end_time(self) -> float:
        """When the last block written ends, as modelled."""
        t = self.free_at
        for arrived, _end, seconds in self.waiting:
            t = max(t, arrived) + seconds
        return t


def tape_blocks(data: bytes, model: MotionModel, scale: float) -> list[tuple[int, float]]:
    """Each LF of a tape with what the control does on reaching it: (offset after the LF,
    seconds it executes), by the motion model; label and blank lines take 0 s."""
    machine = Machine(model, trace=False)
    out: list[tuple[int, float]] = []
    pos = 0
    for number, raw in enumerate(data.split(b"\n")[:-1], 1):
        pos += len(raw) + 1
        text = raw.replace(b"\x00", b"").replace(b"\r", b"").decode("latin-1")
        if "%" in text:
            out.append((pos, 0.0))
            continue
        block = gcode.parse_block(number, text, [])
        seconds = machine.step(block).seconds / scale if block.words else 0.0
        out.append((pos, seconds))
    return out
