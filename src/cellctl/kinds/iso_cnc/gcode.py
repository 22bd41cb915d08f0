"""The G-code check (RS-274, Fanuc M-series dialect), no I/O::

    found = check(text, CheckOptions(o_digits=4))
    for f in found:
        print(f.format("O1234.nc"))      # O1234.nc:12:5: G02 and G03 in one block (group 1)
    for block in blocks(text):           # what motion.py and the preview run on
        block.line, block.get("X"), block.g_codes

Why a table of words and not a PyPI parser: the candidates installable here are ``pygcode``
(0.2.1, last released 2017: LinuxCNC's dialect, no O-number or ``%`` framing, no column in its
errors), ``gcodeparser`` (0.3.0: splits a line into a command and its parameters, for 3-D
printers; no modal groups, ranges or arcs) and ``gcode-lib`` (3-D printer files). None checks
Fanuc's words, ranges and groups with a line and a column, so the dialect is the two tables
below (:data:`WORDS`, :data:`G_GROUPS`), one place for each fact, read by the check and by
the motion model.

What is checked: every character is a word (letter + number), a comment ``( )`` (Fanuc's do
not nest: a ``(`` inside one is an error, as is one left open at the end of its block) or
``;`` to the end of the line; each word's range and whether it must be whole; a letter given
twice in a block; two G codes of one modal group (or two M codes of one group) in a block;
arcs (I/J/K or R, not both; the start and end radii agree within ``arc_tolerance_mm``; R no
shorter than half the chord); G01/G02/G03 before any F, or at F0 (said with where the F0 is);
the O-number (present, 1 to the largest of ``o_digits`` digits) and ``%`` framing (only as a
line of its own, at the start and end: a ``%`` inside a block, a comment's too, would end the
program there on the control).

Hostile input stays bounded: a text over ``max_bytes`` or ``max_blocks`` (cellctl's caps, not
a control's: a drip-feed's are far wider than a read-in's) is refused whole, a block over
``max_block`` characters is refused and not parsed, at most ``max_findings`` are returned (then
checking stops: a last note, no problem itself, says where and how many more were found;
:func:`counted` counts them), and :func:`check` keeps one block at a time.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field

from pydantic import BaseModel, ConfigDict, Field

from cellctl.kinds.iso_cnc.words import (  # the dialect's tables (re-exported here)
    ARCS,
    FEED_MOVES,
    G_GROUPS,
    M_GROUPS,
    PROGRAM_ENDS,
    WORDS,
    WordRule,
)

__all__ = ["ARCS", "FEED_MOVES", "G_GROUPS", "M_GROUPS", "PROGRAM_ENDS", "WORDS", "WordRule"]


class CheckOptions(BaseModel):
    """What the check takes from the machine's options."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    o_digits: int = Field(default=4, ge=1, le=8)
    arc_tolerance_mm: float = Field(default=0.01, gt=0, le=10)
    max_bytes: int = Field(default=16 * 1024 * 1024, gt=0)
    """The most characters cellctl checks (and so sends): its own cap, not the control's."""
    max_blocks: int = Field(default=500_000, gt=0)
    limit_note: str = Field(default="", max_length=300)
    """Said after a refusal by ``max_bytes`` or ``max_blocks`` (what to do instead)."""
    max_block: int = Field(default=256, gt=0, le=4096)
    max_findings: int = Field(default=100, gt=0)


@dataclass(frozen=True, slots=True)
class Finding:
    """One problem, at a line and column (1-based; column 0: the whole line or file)."""

    line: int
    column: int
    message: str
    error: bool = True
    unlisted: int | None = None
    """Set on the note that ends a check stopped at ``max_findings`` (:func:`check`): how
    many more problems were found, not listed. The note is none of them (:func:`counted`)."""

    def format(self, name: str) -> str:
        where = f"{name}:{self.line}" + (f":{self.column}" if self.column else "")
        return f"{where}: {'' if self.error else 'warning: '}{self.message}"


@dataclass(frozen=True, slots=True)
class Word:
    letter: str
    value: float
    column: int
    text: str


@dataclass(frozen=True, slots=True)
class Block:
    """One block (a line) of a program: its words in order, its comment, its line number."""

    line: int
    words: tuple[Word, ...] = ()
    comment: str = ""
    percent: bool = False
    """The line is a ``%`` (tape start or end)."""

    def get(self, letter: str) -> float | None:
        for w in self.words:
            if w.letter == letter:
                return w.value
        return None

    def has(self, letter: str) -> bool:
        return any(w.letter == letter for w in self.words)

    @property
    def g_codes(self) -> list[float]:
        return [w.value for w in self.words if w.letter == "G"]

    @property
    def m_codes(self) -> list[int]:
        return [int(w.value) for w in self.words if w.letter == "M"]


_TOKEN = re.compile(r"[ \t]+|([A-Za-z])[ \t]*([+-]?(?:\d+\.?\d*|\.\d+))|([A-Za-z])")
#: A block of words and blanks only (most of a CAM program): parsed in one pass.
_PLAIN = re.compile(r"(?:[ \t]*[A-Za-z][ \t]*[+-]?(?:\d+\.?\d*|\.\d+))*[ \t]*")
_WORD = re.compile(r"([A-Za-z])[ \t]*([+-]?(?:\d+\.?\d*|\.\d+))")


def parse_block(number: int, line: str, found: list[Finding]) -> Block:
    """One line as a block; the first thing in it that is not a word or comment is a
    finding (one a block: the rest of a block gone wrong is not checked). ``:`` at its
    start is ``O`` (spec: "some write ``:`` for ``O``")."""
    if line.lstrip(" \t/").startswith(":"):
        line = line.replace(":", "O", 1)
    if _PLAIN.fullmatch(line):
        return Block(
            number,
            tuple(
                Word(m[1].upper(), float(m[2]), m.start() + 1, m[1].upper() + m[2])
                for m in _WORD.finditer(line)
            ),
        )
    words: list[Word] = []
    comment: list[str] = []
    if line.strip() == "%":
        return Block(number, percent=True)
    if "%" in line:  # one finding for the block; the rest is checked as if it were a blank
        found.append(Finding(number, line.index("%") + 1, percent_inside(line)))
        line = line.replace("%", " ")
    i, n = 0, len(line)
    if line.startswith("/"):  # block delete: the block is still checked
        i = 1
    while i < n:
        c = line[i]
        if c == "(":
            end = line.find(")", i + 1)
            inner = line[i + 1 : end if end >= 0 else n]
            nested = inner.find("(")
            if nested >= 0:
                found.append(
                    Finding(number, i + 2 + nested, "( inside a comment (they do not nest)")
                )
                break
            if end < 0:
                found.append(Finding(number, i + 1, "comment not closed in its block"))
                break
            comment.append(inner)
            i = end + 1
            continue
        if c == ";":
            comment.append(line[i + 1 :])
            break
        if c == ")":
            found.append(Finding(number, i + 1, ") without its ("))
            break
        m = _TOKEN.match(line, i)
        if m is None:
            shown = repr(c) if c.isprintable() and c.isascii() else f"byte 0x{ord(c):02X}"
            macro = " (macro B: # variables, [ ] expressions are not checked)" if c in "#[]" else ""
            found.append(Finding(number, i + 1, f"{shown} is not part of a word{macro}"))
            break
        if m.group(3) is not None:
            found.append(Finding(number, i + 1, f"{m.group(3).upper()} without a number"))
            break
        elif m.group(1) is not None:
            letter, text = m.group(1).upper(), m.group(2)
            words.append(Word(letter, float(text), i + 1, letter + text))
        i = m.end()
    return Block(number, tuple(words), " ".join(comment))


def percent_inside(line: str) -> str:
    """What a ``%`` inside ``line`` does on the control (it ends the program), in words."""
    at = line.index("%")
    where = "a comment" if line.rfind("(", 0, at) > line.rfind(")", 0, at) else "a block"
    keeps = f"only {line[:at].strip()!r} of this block" if line[:at].strip() else "nothing"
    return (
        f"% inside {where}: a % starts and ends a transmission, so the control ends the "
        f"program there and keeps {keeps} and no block after it (write PCT or the like instead)"
    )


def _lines(text: str) -> Iterator[tuple[int, str]]:
    start, number = 0, 1
    while start < len(text):
        end = text.find("\n", start)
        if end < 0:
            end = len(text)
        yield number, text[start:end].replace("\r", "").replace("\x00", "")
        start, number = end + 1, number + 1


def _parsed(text: str, options: CheckOptions, found: list[Finding]) -> Iterator[Block]:
    for number, line in _lines(text):
        if len(line) > options.max_block:
            found.append(
                Finding(number, 0, f"block of {len(line)} characters (at most {options.max_block})")
            )
            yield Block(number)  # unparsed, as an empty line: check() counts what it found
            continue
        yield parse_block(number, line, found)


def blocks(text: str, options: CheckOptions | None = None) -> list[Block]:
    """The program's blocks (lines too long to be one are left out: :func:`check` says so)."""
    return list(iter_blocks(text, options))


def iter_blocks(text: str, options: CheckOptions | None = None) -> Iterator[Block]:
    """:func:`blocks` one at a time (a long program is never held as blocks)."""
    chosen = options or CheckOptions()
    if len(text) > chosen.max_bytes or text.count("\n") > chosen.max_blocks:
        return
    for b in _parsed(text, chosen, []):
        if b.words or b.percent:
            yield b


@dataclass
class _State:
    """What the check follows from block to block."""

    motion: float | None = None
    feed: float | None = None
    feed_at: tuple[int, int, str] = (0, 0, "")
    """Where the feed in force was given: line, column, the word (``F0``)."""
    absolute: bool = True
    inch: bool = False
    plane: int = 17
    position: dict[str, float | None] = field(
        default_factory=lambda: {"X": None, "Y": None, "Z": None}
    )


_PLANES = {17: ("X", "Y", "I", "J"), 18: ("Z", "X", "K", "I"), 19: ("Y", "Z", "J", "K")}


def _check_words(block: Block, options: CheckOptions, found: list[Finding]) -> None:
    seen: dict[str, Word] = {}
    groups: dict[int, Word] = {}
    m_groups: dict[str, Word] = {}
    for w in block.words:
        rule = WORDS.get(w.letter)
        if rule is None:
            found.append(
                Finding(block.line, w.column, f"{w.letter} is not a word this control reads")
            )
            continue
        if w.letter not in "GM" and w.letter in seen:
            found.append(Finding(block.line, w.column, f"{w.letter} twice in one block"))
        seen[w.letter] = w
        if w.letter == "O":
            problem = _o_number_problem(w, options.o_digits)
            if problem:
                found.append(Finding(block.line, w.column, problem))
                continue
        if not rule.low <= w.value <= rule.high:
            found.append(
                Finding(
                    block.line,
                    w.column,
                    f"{w.text}: {rule.meaning} out of range {_plain(rule.low)} to "
                    f"{_plain(rule.high)}",
                )
            )
        elif rule.whole and w.value != int(w.value):
            found.append(Finding(block.line, w.column, f"{w.text}: {rule.meaning} must be whole"))
        if w.letter == "G":
            group = G_GROUPS.get(w.value)
            if group is None:
                found.append(Finding(block.line, w.column, f"{w.text}: no such G code"))
            elif group and group in groups:
                other = groups[group].text
                found.append(
                    Finding(
                        block.line, w.column, f"{other} and {w.text} in one block (group {group})"
                    )
                )
            elif group:
                groups[group] = w
        elif w.letter == "M":
            mgroup = M_GROUPS.get(int(w.value))
            if mgroup is not None and mgroup in m_groups:
                other = m_groups[mgroup].text
                found.append(
                    Finding(block.line, w.column, f"{other} and {w.text} in one block ({mgroup})")
                )
            elif mgroup is not None:
                m_groups[mgroup] = w


def _plain(value: float) -> str:
    """A range's bound as a user writes it: ``99999999``, ``99999.999``, never ``1e+08``."""
    return f"{value:f}".rstrip("0").rstrip(".")


def _o_number_problem(w: Word, digits: int) -> str:
    """What is wrong with program number ``w`` on a control of ``digits`` digits (``""``:
    nothing): its range is 1 to 9999 on a 4-digit control, not the word's widest."""
    high = 10**digits - 1
    if w.value != int(w.value):
        return f"{w.text}: program number must be whole"
    if w.value > high:
        return f"{w.text}: more than {digits} digits (this control's programs are O1 to O{high})"
    if w.value < 1:
        return f"{w.text}: program number out of range 1 to {high} (a {digits}-digit control)"
    return ""


def _check_motion(block: Block, state: _State, options: CheckOptions, found: list[Finding]) -> None:
    for g in block.g_codes:
        group = G_GROUPS.get(g)
        if group == 1:
            state.motion = g
        elif group == 9:
            state.motion = None if g == 80 else g
        elif group == 3:
            state.absolute = g == 90
        elif group == 6:
            state.inch = g == 20
        elif group == 2:
            state.plane = int(g)
        elif g in (28.0, 30.0, 53.0, 92.0, 52.0) or group == 14:
            state.position = dict.fromkeys(state.position)
    f = next((w for w in block.words if w.letter == "F"), None)
    if f is not None:
        state.feed, state.feed_at = f.value, (block.line, f.column, f.text)
    moves = any(block.has(a) for a in "XYZ")
    one_shot = any(G_GROUPS.get(g) == 0 for g in block.g_codes)
    if not moves or one_shot:
        return
    if state.motion in FEED_MOVES and state.feed is None:
        found.append(
            Finding(block.line, 0, f"G{state.motion:02.0f} move with no feed: no F before it")
        )
    elif state.motion in FEED_MOVES and not state.feed:
        line, column, text = state.feed_at
        said = f"G{state.motion:02.0f} move with a feed of zero ({text}"
        if line == block.line:  # pointed at the F word itself
            found.append(Finding(line, column, f"{said}): the axes would not move"))
        else:
            found.append(
                Finding(
                    block.line,
                    0,
                    f"{said} at line {line}, column {column}, is the feed in force): "
                    "the axes would not move",
                )
            )
    scale = 25.4 if state.inch else 1.0
    start = dict(state.position)
    end: dict[str, float | None] = {}
    for axis in "XYZ":
        value = block.get(axis)
        old = start[axis]
        if value is None:
            end[axis] = old
        elif state.absolute:
            end[axis] = value * scale
        else:
            end[axis] = None if old is None else old + value * scale
    if state.motion in ARCS:
        _check_arc(block, state, start, end, scale, options, found)
    state.position = end


def _check_arc(
    block: Block,
    state: _State,
    start: dict[str, float | None],
    end: dict[str, float | None],
    scale: float,
    options: CheckOptions,
    found: list[Finding],
) -> None:
    a, b, ia, ib = _PLANES[state.plane]
    has_r = block.has("R")
    has_ijk = any(block.has(x) for x in "IJK")
    name = f"G{state.motion:02.0f}"
    if has_r and has_ijk:
        found.append(Finding(block.line, 0, f"{name} with both R and I/J/K"))
        return
    if not has_r and not has_ijk:
        found.append(Finding(block.line, 0, f"{name} without I/J/K or R"))
        return
    sa, sb, ea, eb = start[a], start[b], end[a], end[b]
    if sa is None or sb is None or ea is None or eb is None:
        return  # the start is not known here (after a reference return, a new origin)
    tol = options.arc_tolerance_mm
    if has_r:
        r = abs((block.get("R") or 0.0) * scale)
        chord = math.hypot(ea - sa, eb - sb)
        if chord > 2 * r + tol:
            column = next(w.column for w in block.words if w.letter == "R")
            found.append(
                Finding(
                    block.line,
                    column,
                    f"{name}: R{r:g} is shorter than half the chord ({chord / 2:.3f} mm)",
                )
            )
        return
    ca = sa + (block.get(ia) or 0.0) * scale
    cb = sb + (block.get(ib) or 0.0) * scale
    r0 = math.hypot(sa - ca, sb - cb)
    r1 = math.hypot(ea - ca, eb - cb)
    if abs(r0 - r1) > tol:
        found.append(
            Finding(
                block.line,
                0,
                f"{name}: start radius {r0:.4f} and end radius {r1:.4f} differ "
                f"by more than {tol:g} mm",
            )
        )


def too_long(characters: int, options: CheckOptions) -> Finding:
    """What :func:`check` says of a text over ``options.max_bytes`` (or a file's reader):
    cellctl's own cap, said as such (the control never saw the program)."""
    return Finding(
        1,
        0,
        f"{characters} characters: more than {options.max_bytes}, the most cellctl "
        f"checks{options.limit_note}",
    )


def unpadded(text: str) -> str:
    """``text`` without the NUL and SUB (Ctrl-Z: a DOS editor's end of file) padding after
    its closing ``%``, which the control never reads."""
    body = text.rstrip("\x00\x1a\r\n \t")
    return body + "\n" if body.endswith("%") and "\x1a" in text[len(body) :] else text


def check(text: str, options: CheckOptions | None = None) -> list[Finding]:
    """Every problem of ``text``, in order (errors and warnings: :attr:`Finding.error`)."""
    chosen = options or CheckOptions()
    found: list[Finding] = []
    text = unpadded(text)
    if len(text) > chosen.max_bytes:
        return [too_long(len(text), chosen)]
    lines = text.count("\n")
    if lines > chosen.max_blocks:
        said = f"{lines} blocks: more than {chosen.max_blocks}, the most cellctl checks"
        return [Finding(1, 0, said + chosen.limit_note)]
    state = _State()
    percents: list[int] = []
    first_block: Block | None = None
    last_block: Block | None = None
    closed_at = 0
    for block in _parsed(text, chosen, found):
        if len(found) > chosen.max_findings:
            break
        if block.percent:
            percents.append(block.line)
            if len(percents) == 2:
                closed_at = block.line
            elif len(percents) > 2:
                found.append(Finding(block.line, 1, "% after the closing %"))
            continue
        if not block.words:
            continue
        if closed_at:
            if closed_at > 0:
                found.append(
                    Finding(block.line, 1, "text after the closing %: a control never reads it")
                )
                closed_at = -1
            continue
        if first_block is None:
            first_block = block
        last_block = block
        _check_words(block, chosen, found)
        _check_motion(block, state, chosen, found)
    if len(found) > chosen.max_findings:
        # Stopped before the program's end: its ending and closing % are not checked.
        return _stopped(found, chosen.max_findings)
    if first_block is None:
        found.append(Finding(1, 0, "no blocks: an empty program"))
    elif not first_block.has("O"):
        found.append(
            Finding(
                first_block.line,
                1,
                "no O-number: the program's first block must be O and its number",
            )
        )
    if percents and len(percents) == 1:
        found.append(Finding(percents[0], 1, "% not closed: the tape has no ending %", error=False))
    if last_block is not None and not PROGRAM_ENDS & set(last_block.m_codes):
        found.append(
            Finding(
                last_block.line, 0, "the program does not end with M30, M02 or M99", error=False
            )
        )
    return _stopped(found, chosen.max_findings) if len(found) > chosen.max_findings else found


def _stopped(found: list[Finding], listed: int) -> list[Finding]:
    """The first ``listed`` of ``found``, then the note of a check stopped where the last
    was found: an error itself (a program not checked to its end never goes out), and
    counted as no problem (:func:`counted`)."""
    more = sum(1 for f in found[listed:] if f.error)
    note = f"checking stopped here: {more} more problem{_s(more)} found, not listed"
    return [*found[:listed], Finding(found[-1].line, 0, note, unlisted=more)]


def _s(count: int) -> str:
    return "" if count == 1 else "s"


def counted(findings: list[Finding]) -> str:
    """How many problems (errors) ``findings`` (from :func:`check` or :func:`errors`) hold,
    in words: ``"3 problem(s)"`` (as every ``check`` command counts), or for a check that
    stopped, ``"1318 problems found before checking stopped at line 3 (the first 100
    listed)"``: its last note is none of them."""
    listed = sum(1 for f in findings if f.error and f.unlisted is None)
    note = next((f for f in findings if f.unlisted is not None), None)
    if note is None or note.unlisted is None:
        return f"{listed} problem(s)"
    total = listed + note.unlisted
    return (
        f"{total} problem{_s(total)} found before checking stopped at line {note.line} "
        f"(the first {listed} listed)"
    )


def errors(text: str, options: CheckOptions | None = None) -> list[Finding]:
    """Only the errors (what stops a program from going out)."""
    return [f for f in check(text, options) if f.error]
