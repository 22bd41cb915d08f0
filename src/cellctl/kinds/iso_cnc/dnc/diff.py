"""``cellctl dnc diff``: a program the control punched against what was sent to it.

Both sides are compared block by block as written: ``%`` framing lines, leader, trailer, CR
and NUL gone, trailing spaces and empty blocks dropped. Not as the control keeps them
(:func:`~cellctl.kinds.iso_cnc.tape.unframe`): a ``%`` inside a sent block ends the program
on the control, and the shorter copy it punches must differ from what was sent. Controls
differ in what else they change when they punch: ``spaces=False`` also ignores the spaces
inside blocks (a Fanuc punches ``G01X10.Y5.`` for ``G01 X10. Y5.``),
``case=False`` the case of letters in comments::

    result = compare(sent_bytes, received_bytes, sent_name="sent/O1234_...", received_name=...)
    result.same          # True when the machine holds what was sent
    print(result.text)   # a unified diff, block numbers as the control counts them
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass

#: Lines of a diff shown (a whole program rewritten at the machine makes a long one).
MAX_DIFF_LINES = 2000


@dataclass(frozen=True)
class Comparison:
    """The outcome of :func:`compare`: equal or not, and the diff as text."""

    same: bool
    blocks_sent: int
    blocks_received: int
    text: str


def blocks(data: bytes, *, spaces: bool = True, case: bool = True) -> list[str]:
    """The blocks of a program file as they were written (see module docstring): its ``%``
    lines (framing, with their label), leader, trailer, CR and NUL gone. A ``%`` inside a
    block stays: the control ends the program there, so a copy it punched is shorter, and
    that is a difference (never "the copies match")."""
    lines = data.replace(b"\x00", b"").replace(b"\r", b"").decode("latin-1").split("\n")
    marks = [i for i, line in enumerate(lines) if line.strip().startswith("%")]
    if marks:  # between the opening % and the closing one (or the end)
        lines = lines[marks[0] + 1 : marks[1] if len(marks) > 1 else len(lines)]
    out = []
    for line in lines:
        block = line.rstrip()
        if not spaces:
            block = "".join(block.split())
        if not case:
            block = block.upper()
        if block:
            out.append(block)
    return out


def compare(
    sent: bytes,
    received: bytes,
    *,
    sent_name: str = "sent",
    received_name: str = "received",
    spaces: bool = True,
    case: bool = True,
) -> Comparison:
    """Compare a sent program with a received one (see module docstring)."""
    a = blocks(sent, spaces=spaces, case=case)
    b = blocks(received, spaces=spaces, case=case)
    if a == b:
        return Comparison(True, len(a), len(b), "")
    lines = list(difflib.unified_diff(a, b, sent_name, received_name, lineterm="", n=2))
    if len(lines) > MAX_DIFF_LINES:
        cut = len(lines) - MAX_DIFF_LINES
        lines = [*lines[:MAX_DIFF_LINES], f"... {cut} more lines of difference"]
    return Comparison(False, len(a), len(b), "\n".join(lines))
