"""What the iso-cnc driver reports about a transfer (no I/O)::

report = await cnc.read_in(data, progress=lambda p: print(p.chars_sent, p.phase))
report.ended_early          # True when :meth:`IsoCncDriver.end_tape` cut the tape short
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from cellctl.errors import EXIT_CODES, CellctlError, DeviceError, ProtocolError


@dataclass
class TransferProgress:
    """Where a transfer stands (passed to ``progress`` as it goes)."""

    chars_sent: int
    chars_total: int
    chars_per_s: float
    buffer_stops: int
    elapsed_s: float
    eta_s: float
    phase: str  # "waiting" (for DC1), "sending", "stopped" (DC3), "running", "receiving", "done"


@dataclass
class TransferReport:
    """A finished transfer: its totals, and the alarm if the control raised one."""

    chars_sent: int
    chars_total: int
    chars_per_s: float
    buffer_stops: int
    elapsed_s: float
    alarm: int | None = None
    stalls_modelled_s: float = 0.0
    ended_early: bool = False
    """The tape was ended before its last block (the rest of a block, then ``%``)."""


Progress = Callable[[TransferProgress], None]


@dataclass(frozen=True)
class TapeEnd:
    """Where a tape that failed part-way stopped going out (the driver's ``ended_at``):
    ``TapeEnd.of(framed, sent).words(drip=True)`` says it (``the tape ended at 17808 of
    124351 characters, after block 1612 (X161.1 Y0.1): ...``)."""

    sent: int
    total: int
    block: int
    """Blocks of the program sent whole (its O block is the first); 0 before the first."""
    text: str
    """The last of them, as it went out (shortened)."""
    all_out: bool
    """The program's last block and its end were out: only the end of the read was missing."""

    @classmethod
    def of(cls, framed: bytes, sent: int) -> TapeEnd:
        """Where ``framed`` (a tape as the driver frames it) stood with ``sent`` bytes out."""
        first = framed.find(b"%")
        # The program begins after the opening % and its label (up to LF), or after the leader.
        body = framed.find(b"\n", first) + 1 if first >= 0 else 0
        closing = framed.rfind(b"%")
        end = closing if closing > first >= 0 else len(framed.rstrip(b"\x00"))
        sent = min(sent, len(framed))
        block = framed.count(b"\n", body, sent) if sent > body else 0
        text = ""
        if block:
            eol = framed.rfind(b"\n", body, sent)
            start = framed.rfind(b"\n", body, eol) + 1 or body
            raw = framed[start:eol].replace(b"\x00", b"").replace(b"\r", b"")
            text = raw.decode("latin-1").strip()
            text = text if len(text) <= 40 else text[:37] + "..."
        return cls(sent, len(framed), block, text, sent > end)

    def words(self, *, drip: bool) -> str:
        """Where it ended and what the operator needs to know before going on, in words."""
        if self.all_out:
            said = f"all {self.total} characters of its tape were out"
            return said + (": the control may not have run them all" if drip else "")
        said = f"the tape ended at {self.sent} of {self.total} characters"
        said += f", after block {self.block} ({self.text})" if self.block else ", before a block"
        if not drip:
            return said + ": the control holds at most that first part of it: read it in again"
        # Why a restart is the operator's: the blocks after it lean on the modal state the
        # blocks before it set (spec, "Drip-feed"), which a tape begun there would not have.
        return (
            f"{said}: the control ran at most that far (its display shows the block it "
            "stopped at); to go on from a block, set the program's modal state at the "
            "control first (G-codes, work offset, tool, spindle, feed): a drip-feed sends "
            "the program from its top"
        )


def with_words(error: CellctlError, words: str) -> CellctlError:
    """``error`` with ``words`` after its own, of its own type (its exit code, its API
    error type): ``...: the other end closed the link; the tape ended at ...``."""
    if isinstance(error, DeviceError):
        detail = f"{error.detail}; {words}" if error.detail else words
        return type(error)(error.code, error.message, detail=detail)
    if isinstance(error, ProtocolError):
        return type(error)(f"{error.args[0]}; {words}", error.raw)
    try:
        return type(error)(f"{error}; {words}")
    except TypeError:  # a type built otherwise: its family's, same exit code
        kind = next((k for k in EXIT_CODES if isinstance(error, k)), CellctlError)
        return kind(f"{error}; {words}")
