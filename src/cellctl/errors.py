"""One exception tree for cellctl.

Catch :class:`CellctlError` to handle every failure cellctl raises; catch a subclass to
handle one kind::

    try:
        await robot.go(3)
    except DeviceError as e:        # the machine refused: e.code, e.message
        ...
    except LinkError:               # nothing came back in time, or the line closed
        ...

Every error's ``str()`` is a one-line sentence in the user's words (the source's messages).
Protocol errors carry the raw bytes that broke the protocol in ``raw``.
"""

from __future__ import annotations

from collections.abc import Iterable


class CellctlError(Exception):
    """Base of every error cellctl raises."""


class LinkError(CellctlError):
    """The byte link failed: could not open, closed under us, or a wait ran out."""


class LinkTimeout(LinkError):
    """A wait on the link passed its deadline."""


class SignalTimeout(LinkTimeout):
    """A signal (a PLC input, a robot output) did not reach its value in time: the machine
    answered every read, it just did not do the thing (a stuck door, a cycle not done)."""


class LinkClosed(LinkError):
    """The other end closed the link (or the link was closed locally)."""


class ProtocolError(CellctlError):
    """The bytes on the line do not follow the protocol; ``raw`` holds them."""

    def __init__(self, message: str, raw: bytes = b"") -> None:
        self.raw = bytes(raw)
        super().__init__(message)

    def __str__(self) -> str:
        base = super().__str__()
        if not self.raw:
            return base
        return f"{base} (raw: {format_raw(self.raw)})"


class ChecksumError(ProtocolError):
    """A record's checksum does not match its data."""


class FramingError(ProtocolError):
    """A record is malformed: bad hex, wrong byte count, missing CR LF."""


class UnexpectedReply(ProtocolError):
    """The machine answered something the protocol does not allow at this point."""


class DeviceError(CellctlError):
    """The machine itself reported a failure: ``code`` and the source's ``message``."""

    def __init__(self, code: int, message: str, *, detail: str = "") -> None:
        self.code = code
        self.message = message
        self.detail = detail
        text = f"{message} (code {code})"
        super().__init__(f"{text}: {detail}" if detail else text)


class UsageError(CellctlError):
    """Bad input from the caller, refused before any byte went out."""


class MachineInUse(CellctlError):
    """The machine (or the cell) is held by another owner, or is in automatic service:
    refused before any byte went out. The message names the holder and what to do instead."""


class AccessDenied(CellctlError):
    """The control API refused the caller: a missing or wrong token, or a foreign origin."""


#: Exit codes of the command line, one per kind of failure (1 for anything without its own).
EXIT_CODES: dict[type[CellctlError], int] = {
    UsageError: 2,
    LinkError: 3,
    ProtocolError: 4,
    DeviceError: 5,
    MachineInUse: 6,
    AccessDenied: 7,
}


def exit_code(error: CellctlError) -> int:
    """The exit code for ``error``."""
    for kind, code in EXIT_CODES.items():
        if isinstance(error, kind):
            return code
    return 1


def unknown_machine(name: str, known: Iterable[str], where: str = "") -> UsageError:
    """The refusal of a machine name nobody knows, with the names that are known: "unknown
    machine 'cnc9' (known: robot, cnc1, cnc2)"; ``where``: the file that was asked."""
    listed = ", ".join(known) or "none"
    return UsageError(
        f"unknown machine {name!r}{f' in {where}' if where else ''} (known: {listed})"
    )


#: What free text a caller gives (an order id, a reason, a name) must be, in the words a
#: refusal says: it is logged and shown on operators' terminals, where a control character
#: (an escape sequence, a NUL, a line break that forges a log line) would act.
NOT_PRINTABLE = "must be printable text (no control characters)"


def printable(text: str) -> str:
    """``text`` unchanged if it is printable (:meth:`str.isprintable`: no control, format or
    separator characters but the space), else ValueError(:data:`NOT_PRINTABLE`): the check
    of a schema's field (pydantic says it after the field's name)."""
    if not text.isprintable():
        raise ValueError(NOT_PRINTABLE)
    return text


def check_printable(text: str, what: str) -> str:
    """:func:`printable`, refused as UsageError "``what`` must be printable text ..."."""
    try:
        return printable(text)
    except ValueError:
        raise UsageError(f"{what} {NOT_PRINTABLE}") from None


def with_article(word: str) -> str:
    """``word`` with its article, as a message says it: "an operator", "a viewer", "an
    'engraver'" (by its first letter's sound in the kinds' and roles' names: a ``u`` is said
    "you", as in "a UR")."""
    first = word.lstrip("'\"")[:1].lower()
    return ("an " if first in ("a", "e", "i", "o") else "a ") + word


def format_raw(raw: bytes, limit: int = 64) -> str:
    """Show bytes as hex plus printable text, e.g. ``13 11 44 30 |..D0|``."""
    shown = raw[:limit]
    hexpart = " ".join(f"{b:02X}" for b in shown)
    text = "".join(chr(b) if 32 <= b < 127 else "." for b in shown)
    more = f" … +{len(raw) - limit} bytes" if len(raw) > limit else ""
    return f"{hexpart} |{text}|{more}"
