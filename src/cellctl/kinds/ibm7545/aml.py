"""A compiler for the AML/E subset the cell needs, and the instruction encoding it emits.

The real AML/E compiler is not available, so cellctl defines its own instruction encoding: each
D record of a program file carries one instruction, an opcode byte followed by big-endian
operands (:data:`OPCODES`, the one table that the emulator's interpreter reads too).

Source language (statements end at ``;`` or at the end of the line, so several may share a
line; ``name:`` labels the statement after it, on the same line or the next; keywords in any
case; ``--`` starts a comment, also after statements)::

    -- conveyor to CNC 1
    START:  PMOVE(PT(500.0, 100.0, 50.0, 90.0))   -- x, y, z in mm; roll in degrees
            DOWN; GRASP; UP;
            SPEED(50)                              -- half the arm's speed from here on
            WAITI(3, 1)                            -- wait until input 3 is on
            TESTI(4, 1, START)                     -- back to START if input 4 is on
            ZMOVE(120.5)                           -- Z axis only, mm
            WRITEO(5, 0)                           -- switch output 5 off
            DELAY(1.5)                             -- seconds
            RELEASE
            BRANCH(START)
            END

Units and ranges (what the encoding can carry; the controller checks the workspace):

- ``PT(x, y, z, roll)``: x, y, z in mm, roll in degrees, each with at most one decimal, stored in
  tenths as signed 16 bits: -3276.8 .. 3276.7 mm; roll -360.0 .. 360.0 degrees.
- ``DELAY(s)``: seconds, at most one decimal, 0 .. 6553.5.
- ``WAITI(port, value)`` / ``WRITEO(port, value)``: port 1..16, value 0 or 1.
- ``TESTI(port, value, label)``: branch to ``label`` if input ``port`` has ``value``.
- ``SPEED(percent)``: 1..100, whole; ``ZMOVE(z)``: z in mm like a point's.
- ``BRANCH(label)``: a label defined anywhere in the program (``name:`` at the start of a line).
- ``END`` must be the last statement; a program without it is refused.

Use::

    prog = compile_source(text, name="XFER1", partition=1)   # -> ProgramFile
    Path("xfer1.rec").write_text(prog.to_text())
    instructions = decode_program(prog.body)                 # what the emulator runs

Errors are :class:`~cellctl.errors.UsageError` naming the source, line and column.
"""

from __future__ import annotations

import enum
import re
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation

from cellctl.errors import FramingError, UsageError
from cellctl.kinds.ibm7545.records import ProgramFile, Record, encode_record

__all__ = [
    "OPCODES",
    "Instruction",
    "Op",
    "OpSpec",
    "check_program",
    "compile_program",
    "compile_source",
    "decode_instruction",
    "decode_program",
    "encode_instruction",
]


class Op(enum.IntEnum):
    """Opcode byte, the first data byte of each D record."""

    PMOVE = 0x01
    DELAY = 0x02
    GRASP = 0x03
    RELEASE = 0x04
    UP = 0x05
    DOWN = 0x06
    WAITI = 0x07
    WRITEO = 0x08
    BRANCH = 0x09
    END = 0x0A
    SPEED = 0x0B
    ZMOVE = 0x0C
    TESTI = 0x0D


@dataclass(frozen=True)
class OpSpec:
    """How one instruction is encoded: ``fmt`` is the struct format of its operands."""

    fmt: str
    operands: str  # what the operands are, in wire units


#: The instruction encoding, once. Wire units: tenths of mm / degrees / seconds.
OPCODES: dict[Op, OpSpec] = {
    Op.PMOVE: OpSpec(">hhhh", "x, y, z in 0.1 mm; roll in 0.1 degree"),
    Op.DELAY: OpSpec(">H", "time in 0.1 s"),
    Op.GRASP: OpSpec(">", "close the gripper"),
    Op.RELEASE: OpSpec(">", "open the gripper"),
    Op.UP: OpSpec(">", "raise the Z axis"),
    Op.DOWN: OpSpec(">", "lower the Z axis"),
    Op.WAITI: OpSpec(">BB", "input port 1..16, value 0/1: wait until the input has the value"),
    Op.WRITEO: OpSpec(">BB", "output port 1..16, value 0/1"),
    Op.BRANCH: OpSpec(">H", "index of the target instruction (0 = first)"),
    Op.END: OpSpec(">", "end of the program: the cycle completes"),
    Op.SPEED: OpSpec(">B", "speed in percent of the arm's full speed, 1..100"),
    Op.ZMOVE: OpSpec(">h", "z in 0.1 mm: move the Z axis only"),
    Op.TESTI: OpSpec(
        ">BBH",
        "input port 1..16, value 0/1, index of the target instruction: branch if the input "
        "has the value",
    ),
}

PORTS = range(1, 17)
_TENTHS = Decimal("0.1")


@dataclass(frozen=True)
class Instruction:
    """One instruction: opcode and operands in wire units (tenths, ports, indexes)."""

    op: Op
    operands: tuple[int, ...] = ()
    line: int = 0  # source line, 0 when decoded from records

    def __str__(self) -> str:
        return f"{self.op.name}{self.operands if self.operands else ''}"


def encode_instruction(ins: Instruction) -> Record:
    """The D record carrying ``ins``."""
    try:
        packed = struct.pack(OPCODES[ins.op].fmt, *ins.operands)
    except struct.error as e:
        raise UsageError(f"cannot encode {ins}: {e}") from None
    return Record("D", bytes([ins.op]) + packed)


def decode_program(records: Iterable[Record]) -> list[Instruction]:
    """Decode the D records of a program into instructions (the emulator's loader).

    Raises :class:`FramingError` (with the record's data) for an unknown opcode, a wrong
    operand length, a branch outside the program or a port outside 1..16.
    """
    body = list(records)
    return [decode_instruction(rec, len(body)) for rec in body]


def decode_instruction(rec: Record, count: int) -> Instruction:
    """The instruction one D record carries, checked as the controller checks it in a program
    of ``count`` instructions (a branch must land inside it). FramingError says what is wrong."""
    if rec.ident != "D" or not rec.data:
        raise FramingError("program record is not a D record with an opcode", rec.data)
    try:
        op = Op(rec.data[0])
    except ValueError:
        raise FramingError(f"unknown opcode {rec.data[0]:#04x}", rec.data) from None
    fmt = OPCODES[op].fmt
    if len(rec.data) - 1 != struct.calcsize(fmt):
        raise FramingError(f"{op.name} record has the wrong length", rec.data)
    ins = Instruction(op, struct.unpack(fmt, rec.data[1:]))
    if ins.op in (Op.BRANCH, Op.TESTI) and ins.operands[-1] >= count:
        raise FramingError(
            f"{ins.op.name} to instruction {ins.operands[-1]} outside the program "
            f"(instructions 0..{count - 1})",
            rec.data,
        )
    if ins.op is Op.SPEED and not 1 <= ins.operands[0] <= 100:
        raise FramingError(f"SPEED {ins.operands[0]} outside 1..100 percent", rec.data)
    if ins.op in (Op.WAITI, Op.WRITEO, Op.TESTI) and (
        ins.operands[0] not in PORTS or ins.operands[1] not in (0, 1)
    ):
        raise FramingError(
            f"{ins.op.name} with port {ins.operands[0]}, value {ins.operands[1]} out of range "
            "(port 1..16, value 0 or 1)",
            rec.data,
        )
    return ins


def check_program(program: ProgramFile) -> list[Instruction]:
    """Decode every instruction of ``program`` as the controller will, before a byte goes out.

    A UsageError names the file, the line (or the record, for a program built in memory), the
    record as written and what is wrong with it: a controller answers such a record with
    reject 16 "record format error" only after the whole download, and no retry can fix it.
    """
    body = program.body
    if not body:
        raise UsageError(
            f"{program.source}: no instructions between the N record and E0000 "
            "(a program needs at least END, D010A0A)"
        )
    out: list[Instruction] = []
    for index, rec in enumerate(body, start=1):
        try:
            out.append(decode_instruction(rec, len(body)))
        except FramingError as e:
            where = f"line {program.lines[index]}" if program.lines else f"record {index + 1}"
            written = encode_record(rec).decode("ascii").rstrip()
            raise UsageError(
                f"{program.source}, {where}: instruction {index - 1} ({written}): {e.args[0]}"
            ) from None
    return out


# --- compiler ------------------------------------------------------------------------------------

_TOKEN = re.compile(
    r"\s*(?:(?P<num>[-+]?(?:\d+\.?\d*|\.\d+))|(?P<name>[A-Za-z_][A-Za-z0-9_]*)|(?P<punct>[(),:;])"
    r"|(?P<bad>\S))"
)


@dataclass(frozen=True)
class _Tok:
    kind: str  # "num", "name", "punct", "end"
    text: str
    col: int  # 1-based


class _Line:
    def __init__(self, text: str, lineno: int, source: str) -> None:
        self.lineno = lineno
        self.source = source
        self.toks: list[_Tok] = []
        pos = 0
        while pos < len(text):
            m = _TOKEN.match(text, pos)
            if m is None or m.lastgroup is None:  # only trailing whitespace left
                break
            kind = m.lastgroup
            col = m.start(kind) + 1
            if kind == "bad":
                raise self.error(col, f"unexpected character {m.group(kind)!r}")
            self.toks.append(_Tok(kind, m.group(kind), col))
            pos = m.end()
        self.toks.append(_Tok("end", "", len(text.rstrip()) + 1))
        self.i = 0

    def error(self, col: int, message: str) -> UsageError:
        return UsageError(f"{self.source}, line {self.lineno}, column {col}: {message}")

    def peek(self) -> _Tok:
        return self.toks[self.i]

    def take(self) -> _Tok:
        tok = self.toks[self.i]
        if tok.kind != "end":
            self.i += 1
        return tok

    def expect(self, text: str) -> _Tok:
        tok = self.take()
        if tok.text != text:
            found = f"{tok.text!r}" if tok.kind != "end" else "end of line"
            raise self.error(tok.col, f"expected {text!r}, found {found}")
        return tok

    def number(self, what: str, lo: Decimal, hi: Decimal, *, integer: bool = False) -> int:
        """Parse a number; return it in tenths (or as is when ``integer``)."""
        tok = self.take()
        if tok.kind != "num":
            found = f"{tok.text!r}" if tok.kind != "end" else "end of line"
            raise self.error(tok.col, f"bad number for {what}: {found}")
        try:
            value = Decimal(tok.text)
        except InvalidOperation:  # pragma: no cover - the token pattern admits only numbers
            raise self.error(tok.col, f"bad number for {what}: {tok.text!r}") from None
        if not lo <= value <= hi:
            raise self.error(tok.col, f"{what} {tok.text} out of range {lo}..{hi}")
        if integer:
            if value != value.to_integral_value():
                raise self.error(tok.col, f"{what} must be a whole number, not {tok.text}")
            return int(value)
        tenths = value / _TENTHS
        if tenths != tenths.to_integral_value():
            raise self.error(tok.col, f"{what} {tok.text} has more than one decimal")
        return int(tenths)


_MM = (Decimal("-3276.8"), Decimal("3276.7"))
_DEG = (Decimal(-360), Decimal(360))
_NO_ARGS = {"GRASP": Op.GRASP, "RELEASE": Op.RELEASE, "UP": Op.UP, "DOWN": Op.DOWN, "END": Op.END}


def compile_program(text: str, source: str = "<aml>") -> list[Instruction]:
    """Compile AML/E subset source text into instructions (branch targets resolved)."""
    instructions: list[Instruction] = []
    labels: dict[str, int] = {}
    branches: list[tuple[int, str, _Line, int]] = []  # (instruction index, label, line, col)
    end_seen: _Line | None = None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        code = raw.split("--", 1)[0]
        line = _Line(code, lineno, source)
        while line.peek().kind != "end":
            if line.peek().text == ";":  # an empty statement
                line.take()
                continue
            _labels(line, labels, len(instructions), end_seen)
            tok = line.take()
            if tok.kind == "end":
                break
            if end_seen is not None:
                raise line.error(tok.col, f"statement after END (line {end_seen.lineno})")
            if tok.kind != "name":
                raise line.error(tok.col, f"expected a statement, found {tok.text!r}")
            ins, target = _statement(line, tok)
            if target is not None:
                branches.append((len(instructions), target.text.upper(), line, target.col))
            if ins.op is Op.END:
                end_seen = line
            instructions.append(ins)
            rest = line.peek()
            if rest.text == ";":
                line.take()
            elif rest.kind != "end":
                raise line.error(
                    rest.col,
                    f"unexpected {rest.text!r} after {tok.text.upper()}: separate statements "
                    "with ';'",
                )
    if end_seen is None:
        raise UsageError(f"{source}: missing END (the program's last statement)")
    for index, label, line, col in branches:
        if label not in labels:
            raise line.error(col, f"undefined label {label}")
        old = instructions[index]
        instructions[index] = Instruction(old.op, (*old.operands[:-1], labels[label]), old.line)
    return instructions


def _labels(line: _Line, labels: dict[str, int], here: int, end_seen: _Line | None) -> None:
    """Take the ``name:`` labels in front of a statement (several may stand together)."""
    while (
        line.peek().kind == "name"
        and line.toks[line.i + 1].text == ":"
        and line.peek().text.upper() not in _NO_ARGS
    ):
        tok = line.take()
        line.take()
        key = tok.text.upper()
        if end_seen is not None:
            raise line.error(tok.col, f"label {tok.text} after END (line {end_seen.lineno})")
        if key in labels:
            raise line.error(tok.col, f"label {tok.text} defined twice")
        labels[key] = here


def _port_value(line: _Line) -> tuple[int, int]:
    port = line.number("port", Decimal(1), Decimal(16), integer=True)
    line.expect(",")
    value = line.number("value", Decimal(0), Decimal(1), integer=True)
    return port, value


def _label_operand(line: _Line, word: str) -> _Tok:
    target = line.take()
    if target.kind != "name":
        raise line.error(target.col, f"{word} needs a label: {_SYNTAX[word]}")
    return target


_SYNTAX = {
    "BRANCH": "BRANCH(name)",
    "TESTI": "TESTI(port, value, name)",
}


def _statement(line: _Line, tok: _Tok) -> tuple[Instruction, _Tok | None]:
    """One statement after its keyword ``tok``: the instruction, and the label it jumps to."""
    lineno = line.lineno
    word = tok.text.upper()
    if word in _NO_ARGS:
        return Instruction(_NO_ARGS[word], (), lineno), None
    if word not in _WITH_ARGS:
        raise line.error(tok.col, f"unknown statement {tok.text}")
    line.expect("(")
    target: _Tok | None = None
    operands: tuple[int, ...]
    if word == "PMOVE":
        pt = line.take()
        if pt.text.upper() != "PT":
            raise line.error(pt.col, "PMOVE needs a point: PMOVE(PT(x, y, z, roll))")
        line.expect("(")
        coords: list[int] = []
        for axis in ("x", "y", "z"):
            coords.append(line.number(f"{axis} (mm)", *_MM))
            line.expect(",")
        coords.append(line.number("roll (degrees)", *_DEG))
        line.expect(")")
        operands = tuple(coords)
    elif word == "DELAY":
        operands = (line.number("delay (s)", Decimal(0), Decimal("6553.5")),)
    elif word == "SPEED":
        operands = (line.number("speed (percent)", Decimal(1), Decimal(100), integer=True),)
    elif word == "ZMOVE":
        operands = (line.number("z (mm)", *_MM),)
    elif word in ("WAITI", "WRITEO"):
        operands = _port_value(line)
    elif word == "TESTI":
        port, value = _port_value(line)
        line.expect(",")
        target = _label_operand(line, word)
        operands = (port, value, 0)
    else:  # BRANCH
        target = _label_operand(line, word)
        operands = (0,)
    line.expect(")")
    return Instruction(_WITH_ARGS[word], operands, lineno), target


_WITH_ARGS = {
    "PMOVE": Op.PMOVE,
    "DELAY": Op.DELAY,
    "SPEED": Op.SPEED,
    "ZMOVE": Op.ZMOVE,
    "WAITI": Op.WAITI,
    "WRITEO": Op.WRITEO,
    "TESTI": Op.TESTI,
    "BRANCH": Op.BRANCH,
}


def compile_source(text: str, name: str, partition: int = 1, source: str = "<aml>") -> ProgramFile:
    """Compile source text into a program file: N record (name, partition), D records, end."""
    instructions = compile_program(text, source)
    return ProgramFile.build(name, partition, map(encode_instruction, instructions), source)
