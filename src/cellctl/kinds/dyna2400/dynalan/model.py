"""The typed program model the parser builds and everything else reads.

A :class:`Program` is the file as written: its :class:`Line` s in order, each with the line
number as written, the block of the file it sits in, and its parsed :class:`Statement` (or the
reason it could not be parsed). :class:`Problem` is one finding of the parser or validator.
"""

from __future__ import annotations

import enum
from collections.abc import Iterator
from dataclasses import dataclass, field

from cellctl.kinds.dyna2400.dynalan.table import Kind, Units


@dataclass(frozen=True, slots=True)
class Statement:
    """One parsed statement.

    ``values`` holds the numeric fields by name (e.g. ``rate`` of ``FR``, ``target`` of
    ``SKIP TO``, a cycle's ``XL``); ``words`` the axis words of a move or axis line, in order
    (``(("X", 1.0),)``); ``text`` the text fields (``units``, ``axes``, a comment's text).
    """

    kind: Kind
    values: dict[str, float] = field(default_factory=dict)
    words: tuple[tuple[str, float], ...] = ()
    text: dict[str, str] = field(default_factory=dict)

    def value(self, name: str, default: float | None = None) -> float:
        """The numeric field ``name``; ``default`` when absent (KeyError without one)."""
        if name in self.values:
            return self.values[name]
        if default is None:
            raise KeyError(name)
        return default


class Severity(enum.Enum):
    ERROR = "error"
    WARNING = "warning"


@dataclass(frozen=True, slots=True)
class Problem:
    """One finding: where (file row, column, line number as written, file block) and what."""

    severity: Severity
    code: str
    message: str
    row: int  # 1-based line of the file
    column: int  # 1-based column
    number: str | None = None  # line number as written, e.g. "005"
    block: int | None = None  # 1-based block of the file (multi-block files)

    def where(self) -> str:
        """``block 2 line 005`` / ``line 005`` / ``row 12``: the place in the user's words."""
        if self.number is None:
            return f"row {self.row}"
        return f"block {self.block} line {self.number}" if self.block else f"line {self.number}"

    def format(self, filename: str = "<program>") -> str:
        """Linter style: ``PART.DYN:12:5: error [feed-range] line 005: message``."""
        return (
            f"{filename}:{self.row}:{self.column}: {self.severity.value} [{self.code}] "
            f"{self.where()}: {self.message}"
        )


@dataclass(frozen=True, slots=True)
class Line:
    """One line of the file. ``statement`` is None when it could not be parsed."""

    row: int  # 1-based row in the file
    raw: str  # the text as written, without its line ending
    number: int  # line number as written
    block: int  # 1-based block of the file (blocks end at a `900` line)
    statement: Statement | None

    @property
    def label(self) -> str:
        return f"{self.number:03d}"

    @property
    def kind(self) -> Kind | None:
        return self.statement.kind if self.statement else None


@dataclass(frozen=True)
class Program:
    """A parsed DYNALAN file: its lines, the problems found while parsing, and its units.

    ``units`` is what START says, or None when the program has no START (milling programs take
    the units of the setup program that ran before them).
    """

    lines: tuple[Line, ...]
    problems: tuple[Problem, ...] = ()
    units: Units | None = None
    name: str = "<program>"

    @property
    def ok(self) -> bool:
        """True when parsing found no error (run the validator for the full check)."""
        return not any(p.severity is Severity.ERROR for p in self.problems)

    def statements(self) -> Iterator[Statement]:
        for line in self.lines:
            if line.statement is not None:
                yield line.statement

    @property
    def block_count(self) -> int:
        """Blocks as written in the file (each closed by `SKIP TO 900` / `900`)."""
        return max((line.block for line in self.lines), default=0)


class ProgramRole(enum.Enum):
    """What a program is for: the validator applies the rules of its role."""

    AUTO = "auto"  # setup if it has SETUP, end if it is only END, else milling
    SETUP = "setup"
    MILLING = "milling"
    END = "end"
