"""Block splitter: a program of any length as the blocks program execute mode takes.

Usage::

    blocks = split_program(parse_program(text))    # raises SplitError when it cannot
    for block in blocks:
        link_bytes = block.wire()                   # CR LF lines; the caller adds Ctrl-Z
    text_again = join_blocks(blocks)                # block-format file text

Rules (spec, "Program execute mode: blocks" and the project's conventions):

- The file's own blocks (each closed by ``SKIP TO 900`` / ``900``) are kept when they fit; a
  block too long, or a file written as one sequence (numbers wrapping 999 -> 000), is cut into
  blocks of at most 900 lines, closing pair included (898 statements).
- Every block is renumbered 000, 001, ... and closed by ``SKIP TO 900`` / ``900``, so stale
  lines left in the controller's memory by an earlier, longer block can never run.
- A cut never falls inside a REPEAT ... REPEAT END, between a ``SKIP TO`` and its target, or
  before an axis-only line (continuation, ZERO AT centre, drill hole) or a drill's ZH=/ZD=.
  A ``SKIP TO`` whose target lands at the start of the next block becomes ``SKIP TO 900``.
  When no cut fits, :class:`SplitError` says which structure is too long.
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass

from cellctl.errors import UsageError
from cellctl.kinds.dyna2400.dynalan.machine import Entry
from cellctl.kinds.dyna2400.dynalan.model import Line, Program, Statement
from cellctl.kinds.dyna2400.dynalan.parser import is_block_end
from cellctl.kinds.dyna2400.dynalan.table import (
    BLOCK_BODY_MAX,
    BLOCK_END_LINE,
    LINE_END,
    Kind,
)

#: Statements that must stay in the block of the line before them.
_ATTACHED = frozenset({Kind.AXIS, Kind.DRILL_TOP, Kind.DRILL_BOTTOM})


class SplitError(UsageError):
    """The program cannot be cut into blocks; ``row`` is the file row of the culprit."""

    def __init__(self, message: str, row: int = 0, column: int = 1) -> None:
        self.row = row
        self.column = column
        super().__init__(message)


@dataclass(frozen=True, slots=True)
class BlockLine:
    """A line of a block as sent: its new number, its statement text, where it came from."""

    number: int
    text: str  # what follows the number, spacing as written (" GO X 1.000", "   Y 1.000")
    statement: Statement | None
    origin: Line | None = None  # None for lines the splitter wrote (the closing pair)

    def render(self) -> str:
        return f"{self.number:03d}{self.text}"


@dataclass(frozen=True)
class Block:
    """One block: 1-based ``index`` of ``count``, its lines, closing pair included."""

    index: int
    count: int
    lines: tuple[BlockLine, ...]

    def text(self) -> str:
        """The block as file text, one line per row, LF endings."""
        return "".join(line.render() + "\n" for line in self.lines)

    def wire(self) -> bytes:
        """The block as sent: ASCII lines ending CR LF (no Ctrl-Z)."""
        return b"".join(line.render().encode("ascii") + LINE_END for line in self.lines)

    def memory(self) -> dict[int, Entry]:
        """Numbered statements as the controller holds them (text for an unparsed line)."""
        return {
            line.number: line.statement if line.statement is not None else line.text.strip()
            for line in self.lines
        }

    @property
    def statement_count(self) -> int:
        """Lines not counting the closing pair."""
        return len(self.lines) - 2


def _segments(program: Program) -> list[list[Line]]:
    """The file's blocks, without their closing pair."""
    segments: list[list[Line]] = []
    current: list[Line] = []
    for line in program.lines:
        if is_block_end(line):
            if current and current[-1].kind is Kind.SKIP and _target(current[-1]) == 900:
                current.pop()
            segments.append(current)
            current = []
        else:
            current.append(line)
    if current:
        segments.append(current)
    return segments


def _target(line: Line) -> int:
    assert line.statement is not None
    return int(line.statement.value("target"))


def _where(line: Line) -> str:
    return f"line {line.label} (row {line.row})"


def resolve_jumps(items: Sequence[Line]) -> dict[int, int]:
    """``{index of a SKIP TO: index of its target}``; ``len(items)`` means the block's end.

    A target is the next line after the SKIP TO carrying that number; SKIP TO 900 is the
    block's end. Raises :class:`SplitError` for a missing or backward target.
    """
    jumps: dict[int, int] = {}
    places: dict[int, list[int]] = {}
    for i, line in enumerate(items):
        places.setdefault(line.number, []).append(i)
    for i, line in enumerate(items):
        if line.kind is not Kind.SKIP:
            continue
        target = _target(line)
        if target == BLOCK_END_LINE:
            jumps[i] = len(items)
            continue
        rows = places.get(target, [])
        after = bisect_right(rows, i)
        found = rows[after] if after < len(rows) else None
        if found is None:
            back = after > 0
            why = "jumps backwards (the block would never end)" if back else "has no such line"
            raise SplitError(f"SKIP TO {target:03d} at {_where(line)} {why}", line.row)
        jumps[i] = found
    return jumps


def repeat_spans(items: Sequence[Line]) -> list[tuple[int, int]]:
    """``(REPEAT index, REPEAT END index)`` pairs; SplitError when unbalanced."""
    spans: list[tuple[int, int]] = []
    stack: list[int] = []
    for i, line in enumerate(items):
        if line.kind is Kind.REPEAT:
            stack.append(i)
        elif line.kind is Kind.REPEAT_END:
            if not stack:
                raise SplitError(f"REPEAT END at {_where(line)} has no REPEAT", line.row)
            spans.append((stack.pop(), i))
    if stack:
        line = items[stack[-1]]
        raise SplitError(f"REPEAT at {_where(line)} has no REPEAT END in its block", line.row)
    return spans


class _Cuts:
    """Where a cut may fall; a cut at p puts items[p] first in the next block.

    Built in time linear in the lines (a running count of open structures), so a file of any
    size is cut in time proportional to it; the reason a cut is refused is found only when asked.
    """

    def __init__(self, items: Sequence[Line]) -> None:
        self.items = items
        self.spans: list[tuple[int, int, str]] = []
        for o, c in repeat_spans(items):
            self.spans.append(
                (o, c + 1, f"REPEAT at {_where(items[o])} .. REPEAT END at {_where(items[c])}")
            )
        for i, t in resolve_jumps(items).items():
            what = items[t].label if t < len(items) else "900"
            self.spans.append((i, t, f"SKIP TO {what} at {_where(items[i])} and its target"))
        opened = [0] * (len(items) + 2)
        for start, stop, _ in self.spans:
            opened[start + 1] += 1
            opened[stop] -= 1
        self.attached = [False] * (len(items) + 1)
        attached = False
        for p in range(len(items) - 1, 0, -1):
            kind = items[p].kind
            if kind in _ATTACHED:
                attached = True
            elif kind not in (Kind.COMMENT, Kind.BLANK):
                attached = False
            self.attached[p] = attached
        self.inside = [False] * (len(items) + 1)
        depth = 0
        for p in range(len(items) + 1):
            depth += opened[p]
            self.inside[p] = depth > 0

    def allowed(self, p: int) -> bool:
        return not (self.inside[p] or self.attached[p])

    def why(self, p: int) -> str:
        """Why no cut may fall at ``p``: the outermost structure around it."""
        around = [s for s in self.spans if s[0] < p < s[1]]
        if around:
            start, stop, text = max(around, key=lambda s: s[1] - s[0])
            return f"{text} span {stop - start} lines"
        return f"{_where(self.items[p])} belongs with the line before it"


def _chunks(items: Sequence[Line]) -> list[tuple[int, int]]:
    if len(items) <= BLOCK_BODY_MAX:
        return [(0, len(items))]
    cuts = _Cuts(items)
    chunks: list[tuple[int, int]] = []
    start = 0
    while len(items) - start > BLOCK_BODY_MAX:
        limit = start + BLOCK_BODY_MAX
        cut = next((p for p in range(limit, start, -1) if cuts.allowed(p)), None)
        if cut is None:
            culprit = items[limit]
            raise SplitError(
                f"cannot cut this program into blocks of {BLOCK_BODY_MAX} statements: "
                f"{cuts.why(limit)}, more than one block holds",
                culprit.row,
            )
        chunks.append((start, cut))
        start = cut
    chunks.append((start, len(items)))
    return chunks


def _block_lines(items: Sequence[Line], jumps: dict[int, int], s: int, e: int) -> list[BlockLine]:
    lines: list[BlockLine] = []
    for i in range(s, e):
        line = items[i]
        number = i - s
        text = line.raw[3:]
        if i in jumps:
            t = jumps[i]
            target = t - s if s <= t < e else BLOCK_END_LINE
            text = f" SKIP TO {target:03d}"
        lines.append(BlockLine(number, text, line.statement, line))
    closer = Statement(Kind.SKIP, values={"target": float(BLOCK_END_LINE)})
    lines.append(BlockLine(e - s, f" SKIP TO {BLOCK_END_LINE}", closer))
    lines.append(BlockLine(BLOCK_END_LINE, "", Statement(Kind.BLANK)))
    return lines


def split_program(program: Program) -> list[Block]:
    """Cut ``program`` into closed, renumbered blocks of at most 900 lines (see module doc)."""
    pieces: list[list[BlockLine]] = []
    for items in _segments(program):
        jumps = resolve_jumps(items)
        repeat_spans(items)
        for s, e in _chunks(items):
            pieces.append(_block_lines(items, jumps, s, e))
    count = len(pieces)
    return [Block(i + 1, count, tuple(lines)) for i, lines in enumerate(pieces)]


def join_blocks(blocks: Sequence[Block]) -> str:
    """Blocks back to one block-format file (what :func:`split_program` reads back the same)."""
    return "".join(block.text() for block in blocks)
