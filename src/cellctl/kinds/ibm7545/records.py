"""IBM 7545/7547 robot controller records: encode, incremental decode, status tables.

Frame layout (every record, both directions, ASCII)::

    id  bc  data...  cs  CR LF
    D   02  04 40    44  0D 0A      -> b"D02044044\\r\\n"

- ``id``: one letter, ``D`` (data), ``N`` (program header) or ``E`` (end).
- ``bc``: number of data bytes, two hex digits.
- ``data``: each byte as two hex digits (upper case on output, either case accepted).
- ``cs``: sum of the data bytes modulo 256, two hex digits.
- The controller's end-of-data record is the literal ``EG`` CR LF (``E``, ``G`` = data good, no
  byte count); it decodes to :data:`END_GOOD` (``Record("E", b"G")``) and encodes back to ``EG``.

Single control bytes travel outside records: :data:`XON`, :data:`XOFF`, :data:`ACK`, :data:`EOT`.
The host's identifiers ``R``, ``X`` and ``N`` are single bytes too; ``X``/``R`` are followed by
an *operand record*: two decimal-looking digits and CR LF (``b"11\\r\\n"``, see
:func:`encode_operand` / :func:`decode_operand`).

This module does no I/O and keeps no clock. Decoding is incremental, in the pymodbus manner::

    rec, used = decode_record(buf)
    if used:
        del buf[:used]           # used > 0 even when rec is None: skipped echo/NUL bytes
    if rec is None and not used:
        ...                      # need more bytes

A malformed record raises :class:`~cellctl.errors.FramingError` (bad hex, wrong byte count,
missing CR LF) or :class:`~cellctl.errors.ChecksumError`, each carrying the raw bytes; call
:func:`resync` to learn how many bytes to drop before decoding again.

Compiled program files (``.rec``), see ``docs/robot-program-format.md``::

    N09ppnnnnnnnnnnnnnnnncs     N record: 9 data bytes, partition pp (01..05), 8 name bytes
    D....                       D records: one AML/E instruction each (cellctl.kinds.ibm7545.aml)
    E0000                       end record: E, no data bytes, checksum 00

One record per line, no CR LF needed in the file (the driver adds it on the wire), blank lines
ignored. :class:`ProgramFile` parses and validates such a file; :meth:`ProgramFile.with_partition`
retargets it and recomputes the whole N-record checksum.
"""

from __future__ import annotations

import enum
import string
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cellctl.errors import ChecksumError, FramingError, UsageError
from cellctl.files import read_text, reason

__all__ = [
    "ACK",
    "CR",
    "CRLF",
    "DATA_ERRORS",
    "EMULATOR_INPUT_OFF",
    "EMULATOR_INPUT_ON",
    "END_GOOD",
    "END_RECORD",
    "EOT",
    "LF",
    "MACHINE_STATUS_FLAGS",
    "NAME_LENGTH",
    "N_RECORD_LENGTH",
    "PARTITIONS",
    "RECORD_IDENTS",
    "REJECT_CODES",
    "XOFF",
    "XON",
    "DiDo",
    "ExecuteOperand",
    "Ident",
    "MachineStatus",
    "ProgramFile",
    "ReadOperand",
    "Record",
    "checksum",
    "data_error_message",
    "decode_operand",
    "decode_record",
    "emulator_input_of",
    "emulator_input_operand",
    "encode_operand",
    "encode_record",
    "reject_message",
    "resync",
    "select_application_operand",
]

# --- control bytes ----------------------------------------------------------------------------

XON = 0x11  #: DC1: ready to accept the record / a long command has completed
XOFF = 0x13  #: DC3: sent first after every identifier; repeated about every 25 s while busy
ACK = 0x06  #: record received and command completed (host -> controller after D and E too)
EOT = 0x04  #: the controller rejects; read the reject status (R operand 02)
CR = 0x0D
LF = 0x0A
CRLF = b"\r\n"


class Ident(bytes, enum.Enum):
    """Identifier bytes. ``R``/``X``/``N`` go host -> controller, ``D``/``E`` come back."""

    READ = b"R"  # hex 52 (the prose's "53" is an erratum)
    EXECUTE = b"X"
    DOWNLOAD = b"N"
    DATA = b"D"
    END = b"E"


#: Identifiers that start a record with a byte count (what :func:`decode_record` looks for).
RECORD_IDENTS = b"DEN"

# --- operands -----------------------------------------------------------------------------------


class ExecuteOperand(enum.IntEnum):
    """Operands of the X (execute) transaction, written as two decimal-looking digits."""

    RETURN_HOME = 11  #: answered Xoff at once, Xoff every ~25 s while moving, Xon when home
    AUTO = 20  #: auto-execution mode; robot state 1
    START_CYCLE = 22  #: run the selected application; robot state 2
    STOP_CYCLE = 23  #: back to state 1 (answered Xoff then Xon by the emulator, Ack by the prose)
    ERRESET = 24  #: error reset: **assumed** (not in the source), keep it configurable
    SELECT_APPLICATION_1 = 31  #: 31..35 select partition 1..5
    SELECT_APPLICATION_5 = 35


PARTITIONS = range(1, 6)  #: the controller's program partitions


def select_application_operand(partition: int) -> int:
    """Operand that selects ``partition`` (1..5): 31..35."""
    if partition not in PARTITIONS:
        raise UsageError(f"partition must be 1..5, not {partition}")
    return ExecuteOperand.SELECT_APPLICATION_1 + partition - 1


#: Emulator-only X operands, not the 7545's (a real controller rejects them: 32, undefined
#: record). A robot emulator with no PLC behind it takes its inputs from the host this way:
#: 40 + N drives input N (1..16) on, 60 + N off (``cellctl robot io set N on|off``).
EMULATOR_INPUT_ON = 40
EMULATOR_INPUT_OFF = 60
#: The reject a real controller answers an emulator-only operand with (undefined record).
UNDEFINED_RECORD = 32


def emulator_input_operand(port: int, value: bool) -> int:
    """The emulator-only operand that drives input ``port`` (1..16) to ``value``."""
    if port not in range(1, 17):
        raise UsageError(f"input must be 1 to 16, not {port}")
    return (EMULATOR_INPUT_ON if value else EMULATOR_INPUT_OFF) + port


def emulator_input_of(operand: int) -> tuple[int, bool] | None:
    """``(port, value)`` of an emulator-only input operand; None for any other operand."""
    for base, value in ((EMULATOR_INPUT_ON, True), (EMULATOR_INPUT_OFF, False)):
        if base < operand <= base + 16:
            return operand - base, value
    return None


class ReadOperand(enum.IntEnum):
    """Operands of the R (read) transaction and the D record each one returns."""

    MACHINE_STATUS = 1  #: 2 bytes: :class:`MachineStatus`
    REJECT_STATUS = 2  #: 1 byte: a :data:`REJECT_CODES` key
    DIDO = 10  #: 4 bytes: :class:`DiDo` (layout deduced from the source's listing)


# --- status tables ------------------------------------------------------------------------------

#: Machine status, first byte: bit flags (several may be set at once). 0 = no error.
MACHINE_STATUS_FLAGS: dict[int, str] = {
    128: "servo error",
    64: "power failure",
    32: "overrun",
    16: "over time",
    8: "transmission error",
    4: "data error",
}

#: Machine status, second byte: which data error (meaningful when flag 4 is set).
DATA_ERRORS: dict[int, str] = {
    0: "no data error",
    1: "bus error",
    2: "memory test error",
    17: "arithmetic error",
    18: "programming error",
    19: "invalid op code",
    20: "invalid data",
    21: "invalid port number",
    22: "stack error",
    64: "point out of workspace",
}

#: Reject status (read with R 02 after the controller sent EOT).
REJECT_CODES: dict[int, str] = {
    0: "no reject status",
    16: "record format error",
    21: "invalid port number",
    32: "undefined record",
    48: "improper startup sequence",
    64: "point out of workspace",
    80: "insufficient memory",
    81: "invalid robot type",
    83: "invalid application number",
    96: "invalid identifier sent before N record",
    112: "Xoff time out (30 seconds)",
    128: "manipulator power off",
}


def reject_message(code: int) -> str:
    """The source's message for a reject code, e.g. ``reject_message(48)``."""
    return REJECT_CODES.get(code, f"unknown reject status {code}")


def data_error_message(code: int) -> str:
    """The source's message for a machine-status data error code, e.g. 64."""
    return DATA_ERRORS.get(code, f"unknown data error {code}")


DATA_ERROR_FLAG = 4
SERVO_ERROR_FLAG = 128
POWER_FAILURE_FLAG = 64
#: Flags with which the arm cannot move: a running cycle was aborted.
HALTING_FLAGS = SERVO_ERROR_FLAG | POWER_FAILURE_FLAG


@dataclass(frozen=True)
class MachineStatus:
    """The 2-byte answer to R 01: ``flags`` (first byte) and ``data_error`` (second byte).

    >>> MachineStatus.from_bytes(b"\\x04\\x40").conditions
    ('data error: point out of workspace',)
    """

    flags: int = 0
    data_error: int = 0

    @classmethod
    def from_bytes(cls, data: bytes) -> MachineStatus:
        """Decode the D record's 2 data bytes."""
        if len(data) != 2:
            raise FramingError(f"machine status needs 2 bytes, got {len(data)}", data)
        return cls(data[0], data[1])

    def to_bytes(self) -> bytes:
        """Encode as the D record's 2 data bytes."""
        return bytes((self.flags, self.data_error))

    @property
    def ok(self) -> bool:
        """True when no flag is set."""
        return self.flags == 0

    @property
    def conditions(self) -> tuple[str, ...]:
        """Each set flag as the source's words, highest bit first; data error explained."""
        out: list[str] = []
        for bit, text in MACHINE_STATUS_FLAGS.items():
            if self.flags & bit:
                if bit == DATA_ERROR_FLAG:
                    text = f"{text}: {data_error_message(self.data_error)}"
                out.append(text)
        unknown = self.flags & ~sum(MACHINE_STATUS_FLAGS)
        if unknown:
            out.append(f"unknown status bits {unknown:#04x}")
        return tuple(out)

    def __str__(self) -> str:
        return "; ".join(self.conditions) or "no machine status error"


@dataclass(frozen=True)
class DiDo:
    """The 4-byte answer to R 10: 16 digital inputs and 16 outputs.

    Masks hold line n in bit n-1. Wire layout (deduced from the listing): inputs 1-8, inputs 9-16,
    outputs 1-8, outputs 9-16, bit 0 = lowest numbered line.
    """

    inputs: int = 0
    outputs: int = 0

    @classmethod
    def from_bytes(cls, data: bytes) -> DiDo:
        """Decode the D record's 4 data bytes."""
        if len(data) != 4:
            raise FramingError(f"DI/DO status needs 4 bytes, got {len(data)}", data)
        return cls(data[0] | data[1] << 8, data[2] | data[3] << 8)

    def to_bytes(self) -> bytes:
        """Encode as the D record's 4 data bytes."""
        i, o = self.inputs, self.outputs
        return bytes((i & 0xFF, i >> 8 & 0xFF, o & 0xFF, o >> 8 & 0xFF))

    def input(self, line: int) -> bool:
        """State of input ``line`` (1..16)."""
        return bool(self.inputs >> _line_bit(line) & 1)

    def output(self, line: int) -> bool:
        """State of output ``line`` (1..16)."""
        return bool(self.outputs >> _line_bit(line) & 1)


def _line_bit(line: int) -> int:
    if not 1 <= line <= 16:
        raise UsageError(f"DI/DO line must be 1..16, not {line}")
    return line - 1


# --- records -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Record:
    """One record: ``ident`` (one ASCII letter) and its data bytes."""

    ident: str
    data: bytes = b""

    def __post_init__(self) -> None:
        if len(self.ident) != 1 or not ("A" <= self.ident <= "Z"):
            raise UsageError(f"record identifier must be one letter A-Z, not {self.ident!r}")
        if len(self.data) > 255:
            raise UsageError(f"a record holds at most 255 data bytes, not {len(self.data)}")

    @property
    def is_end_good(self) -> bool:
        """True for the controller's ``EG`` end-of-data record."""
        return self == END_GOOD


#: The controller's end-of-data record, ``EG`` CR LF on the wire.
END_GOOD = Record("E", b"G")
#: The end record of a program file, ``E0000``.
END_RECORD = Record("E", b"")


def checksum(data: bytes) -> int:
    """Sum of the data bytes modulo 256."""
    return sum(data) & 0xFF


def encode_record(rec: Record) -> bytes:
    """Wire bytes of a record, CR LF included: ``Record("D", b"\\x04\\x40")`` -> ``D02044044``."""
    if rec.is_end_good:
        return b"EG" + CRLF
    body = f"{rec.ident}{len(rec.data):02X}{rec.data.hex().upper()}{checksum(rec.data):02X}"
    return body.encode("ascii") + CRLF


def encode_operand(op: int) -> bytes:
    """Operand record of an X or R transaction: ``encode_operand(1)`` -> ``b"01\\r\\n"``."""
    if not 0 <= op <= 99:
        raise UsageError(f"operand must be 0..99, not {op}")
    return f"{op:02d}".encode("ascii") + CRLF


_HEX = frozenset(string.hexdigits.encode("ascii"))
_DIGITS = frozenset(string.digits.encode("ascii"))


def _terminator(buf: bytes | bytearray, pos: int, start: int) -> int:
    """Length of the record terminator at ``pos`` (0 = need more); raise if there is none.

    CR LF is the protocol's; LF CR is accepted because the source's prose writes the pair in
    that order ("Cr (Hex 0A) and Lf (Hex 0D)") and a host written from the prose sends it so.
    """
    end = len(buf)
    if pos >= end:
        return 0
    first = buf[pos]
    if first in (CR, LF):
        if pos + 1 >= end:
            return 0
        pair = bytes(buf[pos : pos + 2])
        if pair in (b"\r\n", b"\n\r"):
            return 2
    raise FramingError("record does not end with CR LF", bytes(buf[start : pos + 2]))


def decode_record(buf: bytes | bytearray) -> tuple[Record | None, int]:
    """Decode one record from the start of ``buf``.

    Returns ``(record, used)`` for a whole record, ``(None, 0)`` when more bytes are needed, and
    ``(None, n)`` when the first ``n`` bytes are not a record start (echo, NULs: drop them and
    call again). Raises :class:`FramingError` / :class:`ChecksumError` with the raw bytes.
    """
    start = 0
    end = len(buf)
    while start < end and buf[start] not in RECORD_IDENTS:
        start += 1
    if start:
        return None, start
    if end == 0:
        return None, 0
    ident = chr(buf[0])
    if ident == "E" and end >= 2 and buf[1] == ord("G"):
        term = _terminator(buf, 2, 0)
        return (END_GOOD, 2 + term) if term else (None, 0)
    # Check every hex digit already here, so a bad byte fails now rather than after a timeout.
    pos = 1
    while pos < min(end, 3):
        if buf[pos] not in _HEX:
            raise FramingError("bad hex digit in byte count", bytes(buf[: pos + 1]))
        pos += 1
    if end < 3:
        return None, 0
    count = int(bytes(buf[1:3]), 16)
    cs_end = 3 + 2 * count + 2
    while pos < min(end, cs_end):
        byte = buf[pos]
        if byte not in _HEX:
            if byte in (CR, LF):
                raise FramingError(
                    f"wrong byte count: record ends after {(pos - 3) // 2} of "
                    f"{count} data bytes and checksum",
                    bytes(buf[: pos + 1]),
                )
            raise FramingError("bad hex digit in record", bytes(buf[: pos + 1]))
        pos += 1
    if end < cs_end:
        return None, 0
    if cs_end < end and buf[cs_end] in _HEX:
        raise FramingError(
            f"wrong byte count: more than {count} data bytes", bytes(buf[: cs_end + 1])
        )
    term = _terminator(buf, cs_end, 0)
    if not term:
        return None, 0
    raw = bytes(buf[: cs_end + term])
    data = bytes.fromhex(raw[3 : 3 + 2 * count].decode("ascii"))
    sent = int(raw[cs_end - 2 : cs_end], 16)
    if sent != checksum(data):
        raise ChecksumError(
            f"bad checksum: record says {sent:02X}, data sums to {checksum(data):02X}", raw
        )
    return Record(ident, data), cs_end + term


def resync(buf: bytes | bytearray) -> int:
    """How many bytes to drop after a decode error: through the next LF, or all of ``buf``."""
    idx = bytes(buf).find(b"\n")
    return len(buf) if idx < 0 else idx + 1


def decode_operand(buf: bytes | bytearray) -> tuple[int | None, int]:
    """Decode an operand record (two digits, CR LF) from the start of ``buf``.

    Returns ``(operand, used)``, or ``(None, 0)`` when more bytes are needed. Raises
    :class:`FramingError` if the bytes are not two digits and CR LF.
    """
    end = len(buf)
    for pos in range(min(end, 2)):
        if buf[pos] not in _DIGITS:
            raise FramingError("operand is not two digits", bytes(buf[: pos + 1]))
    if end < 2:
        return None, 0
    term = _terminator(buf, 2, 0)
    if not term:
        return None, 0
    return int(bytes(buf[:2])), 2 + term


# --- program files -------------------------------------------------------------------------------

N_RECORD_LENGTH = 9  #: data bytes of an N record: partition + 8 name bytes
NAME_LENGTH = 8  #: application name bytes in the N record (ASCII, padded with spaces)


@dataclass(frozen=True)
class ProgramFile:
    """A compiled AML/E program: an N record, D records, the end record.

    Load and retarget before download::

        prog = ProgramFile.load("prog.rec").with_partition(3)
        for rec in prog.records:
            wire = encode_record(rec)     # the driver sends these, Ack after each

    Construction validates the layout; :meth:`parse` and :meth:`load` also decode every
    instruction. A bad file raises :class:`UsageError` naming the file, the line and the fault.
    """

    records: tuple[Record, ...]
    source: str = "<program>"
    lines: tuple[int, ...] = field(default=(), compare=False)  # each record's file line

    def __post_init__(self) -> None:
        _validate(self.records, self.source, None)

    @classmethod
    def build(
        cls, name: str, partition: int, body: Iterable[Record], source: str = "<program>"
    ) -> ProgramFile:
        """Assemble a program from its name, partition and D records (adds N and end)."""
        if partition not in PARTITIONS:
            raise UsageError(f"{source}: partition must be 1..5, not {partition}")
        encoded = name.upper().encode("ascii", "replace")
        if not 1 <= len(encoded) <= NAME_LENGTH or not all(32 < b < 127 for b in encoded):
            raise UsageError(
                f"{source}: application name must be 1..8 printable ASCII characters, not {name!r}"
            )
        header = Record("N", bytes([partition]) + encoded.ljust(NAME_LENGTH, b" "))
        return cls((header, *body, END_RECORD), source)

    @classmethod
    def parse(cls, text: str, source: str = "<program>") -> ProgramFile:
        """Parse a ``.rec`` file's text (a record a line, blanks ignored), instructions too."""
        records: list[Record] = []
        lines: list[int] = []
        for lineno, line in enumerate(text.splitlines(), start=1):
            stripped = line.strip()
            if not stripped:
                continue
            try:
                rec, used = decode_record(stripped.encode("ascii") + CRLF)
            except UnicodeEncodeError:
                raise UsageError(f"{source}, line {lineno}: not ASCII text") from None
            except (FramingError, ChecksumError) as e:
                raise UsageError(f"{source}, line {lineno}: {e}") from None
            if rec is None or used != len(stripped) + 2:
                raise UsageError(f"{source}, line {lineno}: not a record: {stripped[:40]!r}")
            records.append(rec)
            lines.append(lineno)
        _validate(tuple(records), source, lines)
        program = cls(tuple(records), source, tuple(lines))
        from cellctl.kinds.ibm7545.aml import check_program  # aml builds on this module

        check_program(program)  # every instruction decoded as the controller will
        return program

    @classmethod
    def load(cls, path: str | Path) -> ProgramFile:
        """Read and parse a ``.rec`` file; a missing or unreadable file is a UsageError."""
        try:
            text = read_text(path, "ascii")
        except (OSError, UnicodeDecodeError) as e:
            raise UsageError(f"{path}: cannot read program file: {reason(e)}") from None
        return cls.parse(text, str(path))

    @property
    def partition(self) -> int:
        """The partition the N record names (1..5)."""
        return self.records[0].data[0]

    @property
    def name(self) -> str:
        """The application name from the N record (padding removed)."""
        return self.records[0].data[1:].decode("ascii").rstrip()

    @property
    def body(self) -> tuple[Record, ...]:
        """The D records between the N record and the end record."""
        return self.records[1:-1]

    def with_partition(self, partition: int) -> ProgramFile:
        """The same program aimed at ``partition`` (1..5); the N checksum is recomputed whole.

        (The source overwrote only the checksum's last hex digit, which is wrong whenever the
        change carries into the high digit.)
        """
        if partition not in PARTITIONS:
            raise UsageError(f"partition must be 1..5, not {partition}")
        header = self.records[0]
        new = Record("N", bytes([partition]) + header.data[1:])
        return ProgramFile((new, *self.records[1:]), self.source, self.lines)

    def to_text(self) -> str:
        """The ``.rec`` file text: one record per line, LF line ends."""
        return "".join(encode_record(r).decode("ascii").rstrip("\r\n") + "\n" for r in self.records)


def _validate(records: Sequence[Record], source: str, lines: Sequence[int] | None) -> None:
    def where(i: int) -> str:
        return f"{source}, line {lines[i]}" if lines else f"{source}, record {i + 1}"

    if not records:
        raise UsageError(f"{source}: empty program file (needs an N record, D records, E0000)")
    first = records[0]
    if first.ident != "N":
        raise UsageError(f"{where(0)}: first record must be the N record, not {first.ident}")
    if len(first.data) != N_RECORD_LENGTH:
        raise UsageError(
            f"{where(0)}: N record must have {N_RECORD_LENGTH} data bytes, not {len(first.data)}"
        )
    if first.data[0] not in PARTITIONS:
        raise UsageError(f"{where(0)}: N record partition must be 01..05, not {first.data[0]:02X}")
    if not all(32 <= b < 127 for b in first.data[1:]):
        raise UsageError(f"{where(0)}: N record application name is not printable ASCII")
    if len(records) < 2 or records[-1] != END_RECORD:
        raise UsageError(f"{where(len(records) - 1)}: last record must be the end record E0000")
    for i, rec in enumerate(records[1:-1], start=1):
        if rec.ident != "D":
            raise UsageError(f"{where(i)}: expected a D record, not {rec.ident}")
