"""DYNALAN parser: text to the typed :class:`~cellctl.kinds.dyna2400.dynalan.model.Program`.

Usage::

    program = parse_program(path.read_text(), name=path.name)
    for problem in program.problems:        # syntax only; validate() checks the meaning
        print(problem.format(path.name))

    stmt, problems = parse_statement("GO X 1.000")

and, on the wire, :func:`decode_line` frames what the controller receives::

    used, item = decode_line(buffer)   # 0 = need more; item: line text, END_OF_TRANSMISSION, None

The parser checks spelling only (keywords, numbers, line numbers, comment characters); ranges,
context and flow are the validator's.
"""

from __future__ import annotations

import re
from typing import Final

from cellctl.kinds.dyna2400.dynalan.model import Line, Problem, Program, Severity, Statement
from cellctl.kinds.dyna2400.dynalan.table import (
    AXES,
    AXIS_WORD_KINDS,
    BLOCK_END_LINE,
    COMMENT_CHARS,
    CR,
    CTRL_Z,
    CYCLE_KINDS,
    INTEGER_DIGITS_MAX,
    INTEGER_RE,
    LF,
    LINE_NUMBER_DIGITS,
    LINE_NUMBER_RE,
    NUMBER_MAX,
    NUMBER_RE,
    SETUP_AXES,
    SPECS,
    STATEMENTS,
    FieldType,
    Kind,
    StatementSpec,
    Units,
)


class _EndOfTransmission:
    def __repr__(self) -> str:
        return "END_OF_TRANSMISSION"


#: What :func:`decode_line` returns for Ctrl-Z.
END_OF_TRANSMISSION: Final = _EndOfTransmission()

#: ``(column, code, message)``: a problem inside one statement, column 1-based in the line.
Finding = tuple[int, str, str]


def decode_line(data: bytes | bytearray) -> tuple[int, bytes | _EndOfTransmission | None]:
    """Frame one item off the front of ``data`` as the controller does.

    Returns ``(used, item)``: ``used == 0`` means more bytes are needed; otherwise ``item`` is a
    line's bytes (without its ending), :data:`END_OF_TRANSMISSION` for Ctrl-Z, or None when
    ``used`` bytes were only a line ending. CR and LF each end a line and empty lines are
    skipped, so CR LF, LF CR and LF alone all work. Bytes before a Ctrl-Z without a line ending
    come out as a line first.
    """
    for index, byte in enumerate(data):
        if byte in (CR, LF):
            if index == 0:
                return 1, None
            return index + 1, bytes(data[:index])
        if byte == CTRL_Z:
            if index == 0:
                return 1, END_OF_TRANSMISSION
            return index, bytes(data[:index])
    return 0, None


def encode_line(text: str) -> bytes:
    """One line as sent: ASCII text and CR LF."""
    return text.encode("ascii") + b"\r\n"


def _number(token: str) -> float | None:
    """The value of a number token; None when it is not one or lies beyond ±NUMBER_MAX."""
    if not NUMBER_RE.fullmatch(token):
        return None
    value = float(token)
    return value if abs(value) <= NUMBER_MAX else None


def _bad_number(token: str) -> str:
    if NUMBER_RE.fullmatch(token):
        return f"number {_short(token)} is too large: at most {NUMBER_MAX:,} either way"
    return f"bad number {_short(token)!r}"


def _short(token: str) -> str:
    return token if len(token) <= 24 else f"{token[:20]}..."


def _field(
    spec_kind: Kind, name: str, ftype: FieldType, token: str, column: int
) -> tuple[float | str | None, Finding | None]:
    if ftype is FieldType.NUMBER:
        value = _number(token)
        if value is None:
            return None, (column, "bad-number", _bad_number(token))
        return value, None
    if ftype is FieldType.INTEGER:
        if not INTEGER_RE.fullmatch(token):
            return None, (
                column,
                "bad-number",
                f"bad whole number {_short(token)!r} for {spec_kind.value}",
            )
        if len(token.lstrip("0")) > INTEGER_DIGITS_MAX:
            return None, (
                column,
                "bad-number",
                f"whole number {_short(token)} is too large for {spec_kind.value}",
            )
        return float(int(token)), None
    if ftype is FieldType.LINE:
        if not LINE_NUMBER_RE.fullmatch(token):
            return None, (
                column,
                "bad-number",
                f"bad line number {_short(token)!r}: three digits, 000-999",
            )
        return float(int(token)), None
    return token, None


def _axis_words(
    text: str, start: int, offset: int
) -> tuple[tuple[tuple[str, float], ...], list[Finding]]:
    """Axis words from ``text[start:]``: ``X 1.0 Y 2`` (also ``X1.0``)."""
    findings: list[Finding] = []
    tokens: list[tuple[str, int]] = []
    for match in re.finditer(r"\S+", text[start:]):
        token, col = match.group(), start + match.start() + offset
        head = token[0]
        if len(token) > 1 and head.isalpha() and not token[1].isalpha():
            tokens += [(head, col), (token[1:], col + 1)]
        else:
            tokens.append((token, col))
    words: list[tuple[str, float]] = []
    seen: set[str] = set()
    for i in range(0, len(tokens), 2):
        axis, col = tokens[i]
        if axis not in AXES:
            findings.append(
                (col, "axis-words", f"{_short(axis)!r} is not an axis word (X, Y or Z)")
            )
            return tuple(words), findings
        if i + 1 >= len(tokens):
            findings.append((col, "axis-words", f"axis {axis} has no value"))
            return tuple(words), findings
        value_token, value_col = tokens[i + 1]
        value = _number(value_token)
        if value is None:
            findings.append((value_col, "bad-number", _bad_number(value_token)))
            return tuple(words), findings
        if axis in seen:
            findings.append((col, "axis-words", f"axis {axis} given twice"))
        seen.add(axis)
        words.append((axis, value))
    return tuple(words), findings


def _cycle_params(
    kind: Kind, text: str, start: int, offset: int, lead: int
) -> tuple[dict[str, float], list[Finding]]:
    spec = SPECS[kind]
    allowed = spec.required + spec.optional
    values: dict[str, float] = {}
    findings: list[Finding] = []
    pos = start
    while pos < len(text):
        blank = _SPACES.match(text, pos)
        assert blank is not None
        if blank.end() == len(text):
            break
        match = _KEY_VALUE.match(text, pos)
        if match is None:
            col = blank.end() + offset
            findings.append((col, "syntax", f"{kind.value} takes KEY= value pairs: {spec.syntax}"))
            return values, findings
        key, token = match.group(1), match.group(2)
        key_col, value_col = match.start(1) + offset, match.start(2) + offset
        if key not in allowed:
            names = ", ".join(f"{k}=" for k in allowed)
            findings.append((key_col, "syntax", f"{kind.value} has no {key}= (it takes {names})"))
        elif key in values:
            findings.append((key_col, "syntax", f"{key}= given twice"))
        else:
            value = _number(token)
            if value is None:
                findings.append((value_col, "bad-number", _bad_number(token)))
            else:
                values[key] = value
        pos = match.end()
    missing = [k for k in spec.required if k not in values]
    if missing and not findings:
        names = ", ".join(f"{k}=" for k in missing)
        findings.append((lead + offset, "syntax", f"{kind.value} needs {names}: {spec.syntax}"))
    return values, findings


def _first_chars(pattern: str) -> str:
    """The characters a statement's head can start with (every head starts with a literal)."""
    return "XYZ" if pattern.startswith("[XYZ]") else pattern[0]


#: The statements whose head may start with a given character, in the table's order.
_CANDIDATES: dict[str, tuple[StatementSpec, ...]] = {
    char: tuple(s for s in STATEMENTS if char in _first_chars(s.head.pattern))
    for spec in STATEMENTS
    for char in _first_chars(spec.head.pattern)
}

_SPACES = re.compile(r"\s*")
_KEY_VALUE = re.compile(r"\s*([A-Z]+)\s*=\s*(\S+)")


def _check_words(kind: Kind, text: dict[str, str], columns: dict[str, int]) -> list[Finding]:
    findings: list[Finding] = []
    if kind is Kind.START:
        units = text["units"]
        if units not in {u.value for u in Units}:
            findings.append(
                (columns["units"], "syntax", f"START units are INS or MM, not {_short(units)!r}")
            )
    elif kind is Kind.SETUP:
        bad = sorted(set(text["axes"]) - SETUP_AXES)
        if bad:
            findings.append(
                (columns["axes"], "syntax", f"SETUP > takes letters of zcxyu, not {''.join(bad)!r}")
            )
    elif kind is Kind.FEED:
        axes = text["axes"]
        if any(a not in AXES for a in axes) or len(set(axes)) != len(axes):
            findings.append(
                (
                    columns["axes"],
                    "syntax",
                    f"FR names axes X, Y and Z (e.g. FR XY), not {_short(axes)!r}",
                )
            )
    elif kind is Kind.COMMENT:
        body = text["text"].strip()
        for i, char in enumerate(text["text"]):
            if char not in COMMENT_CHARS:
                findings.append(
                    (
                        columns["text"] + i,
                        "comment",
                        f"comment holds {char!r}: only A-Z 0-9 space . , = _ - are allowed",
                    )
                )
                break
        text["text"] = body
    return findings


def parse_statement(text: str, offset: int = 1) -> tuple[Statement | None, list[Finding]]:
    """Parse one statement (the text after the line number).

    ``offset`` is the column of ``text[0]`` in the line, so findings carry line columns.
    Returns the statement (None when it cannot be built) and the findings.
    """
    stripped = text.rstrip()
    if not stripped.strip():
        return Statement(Kind.BLANK), []
    lead = len(stripped) - len(stripped.lstrip())
    for spec in _CANDIDATES.get(stripped[lead], ()):
        head = spec.head.match(stripped, lead)
        if head is None:
            continue
        kind = spec.kind
        if kind in AXIS_WORD_KINDS:
            start = head.end() if kind is not Kind.AXIS else lead
            words, findings = _axis_words(stripped, start, offset)
            if not findings and not words:
                findings.append(
                    (lead + offset, "axis-words", f"{kind.value} needs an axis word, e.g. X 1.000")
                )
            if findings:
                return None, findings
            return Statement(kind, words=words), []
        if kind in CYCLE_KINDS:
            params, findings = _cycle_params(kind, stripped, head.end(), offset, lead)
            return (None, findings) if findings else (Statement(kind, values=params), [])
        assert spec.body is not None
        match = spec.body.fullmatch(stripped, lead)
        if match is None:
            return None, [(lead + offset, "syntax", f"bad {kind.value}: expected {spec.syntax}")]
        values: dict[str, float] = {}
        words_text: dict[str, str] = {}
        columns: dict[str, int] = {}
        findings = []
        for name, ftype in spec.fields.items():
            token = match.group(name)
            column = match.start(name) + offset
            columns[name] = column
            value, finding = _field(kind, name, ftype, token, column)
            if finding:
                findings.append(finding)
            elif isinstance(value, float):
                values[name] = value
            elif isinstance(value, str):
                words_text[name] = value
        findings += _check_words(kind, words_text, columns)
        if findings:
            return None, findings
        return Statement(kind, values=values, text=words_text), []
    token = stripped.split()[0]
    upper = stripped.upper()
    if upper != stripped and any(s.head.match(upper, lead) for s in STATEMENTS):
        return None, [
            (
                lead + offset,
                "unknown-statement",
                f"{_short(token)!r}: statements are written in capitals",
            )
        ]
    return None, [(lead + offset, "unknown-statement", f"unknown statement {_short(token)!r}")]


def parse_line(raw: str) -> tuple[int | None, Statement | None, list[Finding]]:
    """Parse one numbered line: ``(number, statement, findings)``; number None if unreadable."""
    for i, char in enumerate(raw):
        if not (32 <= ord(char) < 127 or char == "\t"):
            return None, None, [(i + 1, "character", f"character {char!r} is not 7-bit ASCII text")]
    digits = re.match(r"\s*(\d*)", raw)
    assert digits is not None
    number_text = digits.group(1)
    column = digits.start(1) + 1
    if not number_text:
        return None, None, [(column, "line-number", "line does not start with a line number")]
    if len(number_text) != LINE_NUMBER_DIGITS:
        return (
            None,
            None,
            [(column, "line-number", f"line number {number_text!r} must have three digits")],
        )
    end = digits.end(1)
    if end < len(raw) and not raw[end].isspace():
        return None, None, [(end + 1, "line-number", "a space must follow the line number")]
    statement, findings = parse_statement(raw[end:], offset=end + 1)
    return int(number_text), statement, findings


def is_block_end(line: Line) -> bool:
    """The blank ``900`` line that closes a block."""
    return line.number == BLOCK_END_LINE and line.kind is Kind.BLANK


def parse_program(text: str, name: str = "<program>") -> Program:
    """Parse a whole file. Lines that cannot be parsed keep ``statement=None`` and a problem.

    Empty rows are skipped. A blank ``900`` line ends a block of the file; the next line starts
    the next block.
    """
    lines: list[Line] = []
    problems: list[Problem] = []
    block = 1
    units: Units | None = None
    for row, raw in enumerate(text.splitlines(), start=1):
        raw = raw.rstrip("\r\n\x1a")
        if not raw.strip():
            continue
        number, statement, findings = parse_line(raw)
        label = f"{number:03d}" if number is not None else None
        for column, code, message in findings:
            problems.append(Problem(Severity.ERROR, code, message, row, column, label, block))
        if number is None:
            continue
        line = Line(row, raw, number, block, statement)
        lines.append(line)
        if statement is not None and statement.kind is Kind.START and units is None:
            units = Units(statement.text["units"])
        if is_block_end(line):
            block += 1
    return Program(tuple(lines), tuple(problems), units, name)
