"""The control's reader buffer as the driver models it (see the driver's docstring, point 2)
and what the control does at each LF of a tape. No I/O: times are passed in."""

from __future__ import annotations

from array import array
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

from cellctl.kinds.iso_cnc import gcode
from cellctl.kinds.iso_cnc.motion import Machine, MotionModel


@dataclass
class BufferModel:
    """The control's reader buffer as the host models it (see module docstring, point 2)."""

    drip: bool
    store_cps: float = 0.0
    #: blocks not yet written whole: (offset after its LF, seconds it runs), tape order;
    #: taken from :attr:`source` as the tape goes (a long program is never held as blocks)
    unsent: deque[tuple[int, float]] = field(default_factory=deque)
    source: Iterator[tuple[int, float]] | None = None
    #: blocks written whole, not yet started: (when its LF is through, offset, seconds)
    waiting: deque[tuple[float, int, float]] = field(default_factory=deque)
    consumed: int = 0
    free_at: float = 0.0
    started: bool = False
    offset: int = 0
    idle_s: float = 0.0  # modelled stalls: the axes waiting for a block
    stalls: int = 0
    #: the longest stall: (seconds, offset after the LF of the block waited for)
    longest: tuple[float, int] = (0.0, 0)

    def feed(self, blocks: Iterable[tuple[int, float]]) -> None:
        """The tape's blocks (:func:`tape_blocks`), taken one by one as they are written."""
        self.source = iter(blocks)

    def _take(self, upto: int) -> None:
        """Blocks from :attr:`source` until one ends past ``upto`` (the block in flight)."""
        source = self.source
        while source is not None and (not self.unsent or self.unsent[-1][0] <= upto):
            block = next(source, None)
            if block is None:
                self.source = source = None
            else:
                self.unsent.append(block)

    def cut(self, total: int) -> None:
        """The tape now ends at offset ``total``: blocks past it never go out."""
        self._take(total)
        self.source = None
        while self.unsent and self.unsent[-1][0] > total:
            self.unsent.pop()

    def wrote(self, upto: int, through_at: float) -> None:
        """Characters up to offset ``upto`` are written; they are through by ``through_at``."""
        if not self.started and not self.drip:
            self.started, self.free_at = True, through_at
        self._take(upto)
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
                waited = arrived - self.free_at
                self.idle_s += waited
                self.stalls += 1
                self.longest = max(self.longest, (waited, end))
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


def tape_blocks(data: bytes, model: MotionModel, scale: float) -> Iterator[tuple[int, float]]:
    """Each LF of a tape with what the control does on reaching it: (offset after the LF,
    seconds it executes), by the motion model; label and blank lines take 0 s. One at a
    time: a drip-feed of millions of blocks holds only those in the control's buffer."""
    machine = Machine(model, trace=False)
    pos, number = 0, 0
    while (eol := data.find(b"\n", pos)) >= 0:
        raw, pos, number = data[pos:eol], eol + 1, number + 1
        text = raw.replace(b"\x00", b"").replace(b"\r", b"").decode("latin-1")
        if "%" in text:
            yield pos, 0.0
            continue
        block = gcode.parse_block(number, text, [])
        yield pos, machine.step(block).seconds / scale if block.words else 0.0


class ModelledBlocks:
    """:func:`tape_blocks` worked out whole before a byte goes out, kept compact (16 bytes a
    block, not a tuple's hundred): the send loop then only reads them. Modelling a block as
    it is written put the G-code parse inside the loop that must stop within a tolerance's
    characters of a DC3 (10 at 9600 baud: 10 ms, less at a time scale): the control's
    buffer overflowed."""

    def __init__(self, blocks: Iterable[tuple[int, float]]) -> None:
        self.ends = array("q")
        self.seconds = array("d")
        for end, seconds in blocks:
            self.ends.append(end)
            self.seconds.append(seconds)

    def __len__(self) -> int:
        return len(self.ends)

    def __iter__(self) -> Iterator[tuple[int, float]]:
        return zip(self.ends, self.seconds, strict=True)


def modelled_blocks(data: bytes, model: MotionModel, scale: float) -> ModelledBlocks:
    """:func:`tape_blocks` of ``data``, all of them (see :class:`ModelledBlocks`)."""
    return ModelledBlocks(tape_blocks(data, model, scale))


@dataclass(frozen=True)
class DripForecast:
    """What a drip-feed of a tape would do at a line rate, as :class:`BufferModel` sees it
    (the driver's own model): the host writing as fast as the line and the buffer allow."""

    chars: int
    timed: int
    """Blocks that take time."""
    line_s: float
    """The tape's characters on the line, end to end."""
    run_s: float
    """The blocks' motion time (the axes never waiting)."""
    end_s: float
    """From the first character to the last block's end, the waits included."""
    stall_s: float
    stalls: int
    longest_s: float
    longest_block: str
    """The block the axes waited for longest ("" without a stall)."""


def forecast_drip(
    framed: bytes,
    blocks: Iterable[tuple[int, float]],
    char_time: float,
    sender: tuple[int, int],
) -> DripForecast:
    """A drip-feed of ``framed`` (:func:`~cellctl.kinds.iso_cnc.tape.frame`'s tape; its
    ``blocks`` by :func:`tape_blocks`) at ``char_time`` s a character, the host writing as
    :meth:`IsoCncOptions.sender <cellctl.kinds.iso_cnc.options.IsoCncOptions.sender>` says
    (``(burst, limit)``). Pure arithmetic: a 200,000-block tape takes a second or two."""
    burst, limit = sender
    buffer = BufferModel(drip=True)
    run = [0.0, 0]  # the blocks' motion time, and how many take time, as they are taken

    def counted() -> Iterator[tuple[int, float]]:
        for block in blocks:
            if block[1] > 0:
                run[0] += block[1]
                run[1] += 1
            yield block

    buffer.feed(counted())
    total, sent, now = len(framed), 0, 0.0
    while sent < total:
        room = limit - buffer.level(sent, now)
        if room <= 0:
            drain = buffer.next_drain()
            if drain is not None:
                now = max(drain, now + char_time)
                continue
            # Nothing to wait for: a block longer than the room. The driver writes on, the
            # control's DC3 its guard; so does this.
            room = burst
        n = min(burst, total - sent, room)
        now += n * char_time  # back to back: the line never idles while there is room
        sent += n
        buffer.wrote(sent, now)
    end = buffer.end_time()
    buffer.level(sent, end)  # the blocks still waiting start (and may stall) by the end
    waited, offset = buffer.longest
    block = ""
    if buffer.stalls:
        start = framed.rfind(b"\n", 0, offset - 1) + 1
        block = framed[start : offset - 1].decode("latin-1").strip()
    buffer.cut(total)  # every block taken (and counted)
    return DripForecast(
        chars=total,
        timed=int(run[1]),
        line_s=total * char_time,
        run_s=run[0],
        end_s=end,
        stall_s=buffer.idle_s,
        stalls=buffer.stalls,
        longest_s=waited,
        longest_block=block,
    )
