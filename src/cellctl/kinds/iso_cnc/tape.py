"""ISO tape codec (no I/O): the control codes, framing a program for the line, unframing
what came off it, splitting a tape into programs by O-number::

    data = frame("O1234 (PART)\\nG0 X0\\nM30\\n", leader=20, trailer=20, percent=True)
    # b"\\0" * 20 + b"%\\nO1234 (PART)\\nG0 X0\\nM30\\n%" + b"\\0" * 20
    unframe(data)                 # "O1234 (PART)\\nG0 X0\\nM30\\n"
    split_programs(unframe(data)) # [TapeProgram(1234, "PART", "O1234 (PART)\\n...")]

The tape (spec, "The tape format"): NUL leader, ``%`` LF, blocks each ended by LF (EOB), ``%``,
NUL trailer. CR and NUL are ignored; what follows ``%`` up to the first LF is skipped (label
skip). A program starts with ``O`` (or ``:``) and its number.
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass

from cellctl.errors import UsageError


class Code(enum.IntEnum):
    """The control codes (spec, "Control codes"): one table, with who sends each and why."""

    DC1 = 0x11
    DC2 = 0x12
    DC3 = 0x13
    DC4 = 0x14


#: code -> (sent by, meaning), as the spec's table has it.
CONTROL_CODES: dict[Code, tuple[str, str]] = {
    Code.DC1: ("the control", "tape reader start: send me data (also: resume after DC3)"),
    Code.DC2: ("the control", "tape punch designation: data follows from me"),
    Code.DC3: ("the control", "tape reader stop: stop sending"),
    Code.DC4: ("the control", "tape punch release: my data is done"),
}

DC1 = bytes([Code.DC1])
DC2 = bytes([Code.DC2])
DC3 = bytes([Code.DC3])
DC4 = bytes([Code.DC4])
NAK = b"\x15"  # a remote-buffer interface's "the control alarmed" (then NNN LF)
SYN = b"\x16"  # the same interface's "the control was reset" (its alarm cleared)
NUL = 0x00
LF = 0x0A  # EOB in ISO code
CR = 0x0D  # ignored
PERCENT = 0x25  # starts and ends a transmission (ISO "ER")

#: alarm number -> the control's words (spec, "Alarms the host must understand"). A control
#: that reports its alarm on the line sends NAK, the number in three digits, LF.
ALARMS: dict[int, str] = {
    85: "COMMUNICATION ERROR",
    86: "DR OFF",
    87: "BUFFER OVERFLOW",
}
ALARM_MEANINGS: dict[int, str] = {
    85: "parity, framing or overrun on the control's side: line settings or noise",
    86: "the cable or device server lost DSR (DR)",
    87: "the host sent more than the control's tolerance after its DC3",
}


def alarm_report(code: int) -> bytes:
    """How a control reports alarm ``code`` on the line: NAK, three digits, LF."""
    return NAK + b"%03d\n" % code


def parse_alarm(data: bytes) -> tuple[int, int] | None:
    """``(code, bytes used)`` of an alarm report at the start of ``data``; (0, used) for a NAK
    with no number after it; None when more bytes are needed."""
    if not data.startswith(NAK):
        raise ValueError("not an alarm report")
    end = data.find(b"\n", 1)
    if end < 0:
        return None if len(data) < 5 else (0, 1)
    digits = data[1:end]
    return (int(digits), end + 1) if digits.isdigit() and len(digits) <= 3 else (0, 1)


def alarm_state(data: bytes) -> tuple[bool, int | None, bytes]:
    """What a control's own words in ``data`` (its alarm reports, the SYN of a reset) say of
    its alarm, the last of them winning: (whether they said anything, the alarm it is in or
    None after a reset, an unfinished report at the end). Other bytes are skipped."""
    said, code, i = False, None, 0
    while i < len(data):
        byte = data[i]
        if byte == NAK[0]:
            found = parse_alarm(data[i:])
            if found is None:
                return said, code, data[i:]
            number, used = found
            if number:
                said, code = True, number
            i += used
            continue
        if byte == SYN[0]:
            said, code = True, None
        i += 1
    return said, code, b""


#: A program's first block: O (or ``:``) and its number, then maybe a comment as its title.
# The control reads an address in either case (as the G-code check does): ``o1234`` too.
_O_LINE = re.compile(r"[ \t]*[Oo:]([0-9]{1,8})[ \t]*(?:\(([^)\n]*)\)?)?")


@dataclass(frozen=True)
class TapeProgram:
    """One program on a tape: its O-number (0 when it has none), title and text (LF ends)."""

    number: int
    title: str
    text: str


def body_text(text: str) -> str:
    """``text`` as the control keeps it: CR and NUL gone, ``%`` framing stripped (label skip
    after the first ``%``), every block ended by LF."""
    return unframe(text.encode("latin-1", "replace"))


def frame(text: str, *, leader: int = 0, trailer: int = 0, percent: bool = True) -> bytes:
    """``text`` as an ISO tape: NUL leader, ``%`` LF, its blocks (LF each), ``%``, NUL trailer.

    ``text`` may carry its own ``%`` lines (a file as CAM writes it): they are not doubled.
    Raises UsageError for characters a 7-bit ISO tape cannot carry.
    """
    if leader < 0 or trailer < 0:
        raise UsageError("leader and trailer are counts of NUL characters (0 or more)")
    body = body_text(text)
    bad = next((i for i, c in enumerate(body) if ord(c) > 0x7E), None)
    if bad is not None:
        line = body.count("\n", 0, bad) + 1
        raise UsageError(f"line {line}: {body[bad]!r} is not an ISO character")
    head = b"%\n" if percent else b""
    tail = b"%" if percent else b""
    return bytes(leader) + head + body.encode("ascii") + tail + bytes(trailer)


def unframe(data: bytes) -> str:
    """What a control reads from ``data``: NUL and CR dropped, the leader before the first
    ``%`` and the label after it (up to LF) skipped, up to the closing ``%``. Without any
    ``%``, all of it. The last block ends with LF (one is added if the tape lacks it)."""
    clean = data.replace(b"\x00", b"").replace(b"\r", b"")
    start = clean.find(b"%")
    if start >= 0:
        eol = clean.find(b"\n", start)
        if eol < 0:
            return ""
        clean = clean[eol + 1 :]
        end = clean.find(b"%")
        if end >= 0:
            clean = clean[:end]
    text = clean.decode("latin-1")
    if text and not text.endswith("\n"):
        text += "\n"
    return text


def skipped_leader(data: bytes) -> tuple[int, str] | None:
    """Text before a tape's opening ``%`` (line number, the text), which a control skips as
    leader: a ``%`` in the middle of a file drops everything above it. None when only NUL,
    blanks and line ends come before it (or there is no ``%``)."""
    start = data.find(b"%")
    if start <= 0:
        return None
    if data[data.rfind(b"\n", 0, start) + 1 : start].strip(b" \t\r\x00"):
        return None  # a % inside a block: the G-code check refuses it (it ends the program)
    before = data[:start].replace(b"\x00", b"").decode("latin-1")
    for number, line in enumerate(before.split("\n"), start=1):
        if line.strip():
            return number, line.strip()
    return None


def o_number(text: str) -> int | None:
    """The O-number of ``text``'s first block (``O1234`` or ``:1234``); None without one."""
    for line in text.split("\n", 64)[:64]:
        if not line.strip() or line.strip() == "%":
            continue
        found = _O_LINE.match(line)
        return int(found.group(1)) if found else None
    return None


def split_programs(text: str) -> list[TapeProgram]:
    """The programs of a tape's text, each from its O block to before the next one. Blocks
    before the first O block make a program of number 0 (a tape without numbers)."""
    programs: list[TapeProgram] = []
    number, title = 0, ""
    current: list[str] = []
    for line in body_text(text).splitlines(keepends=True):
        found = _O_LINE.match(line)
        if found and not line[found.end() :].strip():
            if any(s.strip() for s in current):
                programs.append(TapeProgram(number, title, "".join(current)))
            number, title = int(found.group(1)), (found.group(2) or "").strip()
            current = [line]
        else:
            current.append(line)
    if any(s.strip() for s in current):
        programs.append(TapeProgram(number, title, "".join(current)))
    return programs


def not_iso_code(name: str, data: bytes) -> str | None:
    """Why program file ``name`` (its bytes ``data``) cannot be a program, when a byte is not
    7-bit ASCII (a binary, or a word processor's file): the one wording of every surface
    (``cellctl dnc send``, ``dnc check``, the console's program picker, the API's
    ``dnc.send``, the kind's check). None when every byte is ASCII."""
    if data.isascii():
        return None
    at = next(i for i, byte in enumerate(data) if byte > 0x7F)
    return f"{name}: not ISO code: byte {at + 1} is 0x{data[at]:02X} (a program is 7-bit ASCII)"


def control_code_name(byte: int) -> str:
    """``DC3`` for 0x13; the byte in hex for anything else (for messages and logs)."""
    try:
        return Code(byte).name
    except ValueError:
        return f"0x{byte:02X}"


def cut_tape(data: bytes, sent: int, *, percent: bool = True) -> bytes | None:
    """``data`` (a framed tape of which ``sent`` bytes are out) ended early the clean way: the
    rest of the block in flight (to its LF), then ``%``, which ends a transmission (spec,
    "The tape format"); without ``%`` framing, an ``M30`` block ends it. The control leaves
    the read as at any tape's end: nothing half a block long is left in it. None when the
    tape's own end is already out or in the block in flight (nothing to cut)."""
    closing = data.rfind(b"%") if percent else len(data.rstrip(b"\x00"))
    if percent and closing <= data.find(b"%"):
        closing = len(data)  # no closing % (a tape framed without one)
    if sent > 0 and data[sent - 1] == LF:
        cut = sent
    elif not percent and not data[:sent].strip(b"\x00"):
        cut = sent  # only leader is out: nothing of a block to finish
    else:
        eol = data.find(b"\n", sent)
        cut = len(data) if eol < 0 else eol + 1
    if cut >= closing:
        return None
    return data[:cut] + (b"%" if percent else b"M30\n")
