"""The remote request: how the operator at the control asks the server for a program.

The convention (per machine, ``[machines.NAME.request]`` of dnc.toml): the operator writes a
tiny program numbered :attr:`RequestConvention.program` (default ``O9999``) whose comment
names the program wanted, and punches it::

    O9999 (LOAD O1234)          the control's next read receives O1234 (into memory)
    O9999 (DRIP O1234)          the control's next read receives a drip-feed of O1234
    O9999 (LOAD O1234 DRIP)     the same as DRIP

The words (``LOAD``, ``DRIP``) are options too, for a shop whose CAM or habit says ``SEND`` or
``DNC``. Case, spaces and where the comment sits (on the O line or the next block) do not
matter; ``:1234`` is taken for ``O1234``. A request program that names no program, or two, is
refused with what it said (the server logs the refusal and keeps the punched program as
received). Any other program punched is a backup: kept as received.

::

    request = parse_request(9999, "(LOAD O1234)", RequestConvention())
    request.program, request.drip           # 1234, False
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field

from cellctl.errors import UsageError

#: The largest O-number (8 digits, the newer controls').
MAX_O_NUMBER = 99_999_999
#: How much of a request program is looked at (a request is a line or two).
MAX_REQUEST_CHARS = 4096


class RequestConvention(BaseModel):
    """``[machines.NAME.request]``: how this machine's operator asks for a program."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    program: int = Field(default=9999, ge=1, le=MAX_O_NUMBER)
    """O-number of the request program the operator punches (``O9999``)."""
    load: str = Field(default="LOAD", pattern=r"^[A-Za-z]{2,12}$")
    """The word before the O-number wanted: the next read receives it into memory."""
    drip: str = Field(default="DRIP", pattern=r"^[A-Za-z]{2,12}$")
    """The word that asks for a drip-feed instead (in place of the load word, or after it)."""
    enabled: bool = True
    """Whether punched request programs are answered (false: kept as received like others)."""


@dataclass(frozen=True)
class Request:
    """A program asked for from the control: its O-number and whether to drip-feed it."""

    program: int
    drip: bool

    def __str__(self) -> str:
        how = "drip-feed" if self.drip else "load"
        return f"{how} O{self.program:04d}"


def parse_request(number: int, text: str, convention: RequestConvention) -> Request | None:
    """The request punched program ``number`` (its text, ``%`` framing removed) makes; None
    when it is not the request program; UsageError naming what it said when it is one that
    cannot be understood."""
    if not convention.enabled or number != convention.program:
        return None
    comments = " ".join(re.findall(r"\(([^()]*)\)", text[:MAX_REQUEST_CHARS]))
    words = [w.upper() for w in re.findall(r"[Oo:]\s*\d+|[A-Za-z]+", comments)]
    load, drip = convention.load.upper(), convention.drip.upper()
    wanted = [int(w[1:]) for w in words if w[0] in "O:" and w[1:].strip().isdigit()]
    said = " ".join(comments.split())[:80] or "no comment"
    if load not in words and drip not in words:
        raise UsageError(
            f"request O{number:04d} ({said}) asks for nothing: write ({load} O1234) or "
            f"({drip} O1234)"
        )
    if len(wanted) != 1:
        raise UsageError(
            f"request O{number:04d} ({said}) must name one program, like ({load} O1234)"
        )
    if not 1 <= wanted[0] <= MAX_O_NUMBER or wanted[0] == number:
        raise UsageError(f"request O{number:04d} ({said}) names no program that can be sent")
    return Request(program=wanted[0], drip=drip in words)
