"""A DNC machine's status as the server keeps it (what the API, the console and the
dashboard show) and its traffic kept for ``traffic.tail``::

    line.status.activity          # Activity.DRIP_FEEDING
    line.status.chars_done, line.status.stall_s
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any

from cellctl.clock import current_clock
from cellctl.errors import CellctlError
from cellctl.link import TrafficLog

#: Chunks of traffic each machine keeps for ``traffic.tail`` (the console's traffic pane).
TRAFFIC_KEEP = 200
#: Seconds a machine's traffic is kept after a client last asked for it.
WATCH_S = 30.0
#: Progress phases passed on at once (the others at most twice a second).
UNTHROTTLED = ("done", "waiting", "stopped", "running")


class TransferStopped(CellctlError):
    """A transfer stopped (by hand, by its sender, by the server stopping): the message says
    where it ended."""


class WatchedTraffic(TrafficLog):
    """A machine's last chunks both ways, kept only while a client looks at them
    (:meth:`watch`, called by ``traffic.tail``, within the last :data:`WATCH_S`): a shop of
    hundreds of links spends nothing on traffic nobody reads."""

    def __init__(self) -> None:
        super().__init__(None, keep=TRAFFIC_KEEP)
        self.until = 0.0

    def watch(self) -> None:
        """Keep what goes both ways for the next :data:`WATCH_S` seconds."""
        self.until = current_clock().now() + WATCH_S

    def record(self, label: str, direction: str, data: bytes, when: float) -> None:
        if when <= self.until:
            super().record(label, direction, data, when)


class Activity(enum.StrEnum):
    """What a DNC machine is doing."""

    IDLE = "idle"
    """Listening for the control (a punch, or a request)."""
    WAITING = "waiting for read"
    """A program is ready: the control's next read (READ / CYCLE START) receives it."""
    READING = "reading"
    """The control reads a program into its memory."""
    DRIP_FEEDING = "drip-feeding"
    """The control runs a program as it arrives."""
    PUNCHING = "punching"
    """The control punches a program to the server."""
    AWAITING_PUNCH = "waiting for punch"
    """Someone waits for the control's next punch (``cellctl dnc receive``)."""
    OFFLINE = "offline"
    """Its link is not open (failed; opened again in a few seconds)."""


@dataclass(frozen=True)
class MachineStatus:
    """One DNC machine's status (what the API, the console and the dashboard show)."""

    name: str
    activity: Activity = Activity.OFFLINE
    program: str | None = None
    phase: str = ""
    """Where a transfer stands: ``preparing`` (checked and framed: not offered to the control
    yet), ``waiting`` (for the control's DC1), ``sending``, ``stopped``
    (a DC3), ``running`` (all sent, the control runs the rest), ``receiving``."""
    chars_done: int = 0
    chars_total: int = 0
    chars_per_s: float = 0.0
    buffer_stops: int = 0
    eta_s: float | None = None
    stall_s: float = 0.0
    """Seconds the machine waited for data during this drip-feed (as the driver reckons it)."""
    since: float = 0.0
    last: str = ""
    """The last thing done, in words (``received O1234 (812 chars)``)."""
    error: str = ""
    pending: str = ""
    """The request waiting for the control's read (``drip-feed O1234``), if any."""
    transfers: int = 0
    failures: int = 0


def progress_dict(p: Any) -> dict[str, Any]:
    """A driver's TransferProgress as the API pushes it."""
    return {
        "phase": str(getattr(p, "phase", "")),
        "chars_sent": int(getattr(p, "chars_sent", 0)),
        "chars_total": int(getattr(p, "chars_total", 0)),
        "chars_per_s": float(getattr(p, "chars_per_s", 0.0)),
        "buffer_stops": int(getattr(p, "buffer_stops", 0)),
        "elapsed_s": float(getattr(p, "elapsed_s", 0.0)),
        "eta_s": getattr(p, "eta_s", None),
        # the driver's modelled stall (the axes waiting for a block), where it gives one
        "stall_s": float(getattr(p, "stall_s", 0.0) or getattr(p, "stalls_modelled_s", 0.0)),
    }


def stopped_progress(s: MachineStatus, words: str) -> dict[str, Any]:
    """The last progress of a transfer stopped before its end (``dnc.stop``, its sender's
    Ctrl-C, the server stopping): its figures as last seen, phase ``ended``, and ``stopped``:
    where it ended, in words (the error that follows says the same)."""
    return {
        "phase": "ended",
        "chars_sent": s.chars_done,
        "chars_total": s.chars_total,
        "chars_per_s": s.chars_per_s,
        "buffer_stops": s.buffer_stops,
        "elapsed_s": 0.0,
        "eta_s": None,
        "stall_s": s.stall_s,
        "stopped": words,
    }


#: What the operator does at the control to start a read, for a read-in and a drip-feed.
START_READ = {
    False: "press READ on the control, in EDIT mode",
    True: "press CYCLE START on the control, in RMT (DNC) mode",
}


def state_words(s: MachineStatus) -> str:
    """A machine's state as the console and dashboard show it; while a program waits for
    the control's read, what the operator does to start it."""
    words = s.activity.value
    if s.activity in (Activity.READING, Activity.DRIP_FEEDING) and s.program:
        words += f" {s.program}"
    if s.activity in (Activity.READING, Activity.DRIP_FEEDING) and s.phase == "preparing":
        return f"{words}: preparing (checking and framing its tape, nothing sent yet)"
    if s.activity in (Activity.READING, Activity.DRIP_FEEDING) and s.phase == "waiting":
        return f"{words}: waiting for read: {START_READ[s.activity is Activity.DRIP_FEEDING]}"
    if s.activity is Activity.WAITING and s.pending:
        drip = s.pending.startswith("drip")
        words += f": {s.pending}: {START_READ[drip]}"
    if s.stall_s > 0 and s.activity is Activity.DRIP_FEEDING:
        words += f", stalled {s.stall_s:.1f} s"
    if s.buffer_stops and s.activity in (Activity.READING, Activity.DRIP_FEEDING):
        # the status model has no field for them: said in the state's words
        words += f", {s.buffer_stops} buffer stop{'s' if s.buffer_stops > 1 else ''}"
    return words


def ended_words(
    why: str, program: str, drip: bool, done: int, total: int, *, running: bool = False
) -> str:
    """A transfer ended early the clean way, in words: ``the DNC server stopped: the
    drip-feed of O5000.nc ended at 1192 of 7626 characters (...)``."""
    what = "drip-feed" if drip else "read-in"
    if drip and running:
        after = "the control runs the blocks it holds, then leaves the read"
    elif drip:
        after = "the control ran the blocks it held and left the read"
    else:
        after = "the control holds the first part of the program: read it in again"
    return (
        f"{why}: the {what} of {program} ended at {done} of {total} characters "
        f"(the rest of its block and % sent: {after})"
    )


#: The words of a stop that came when all of a transfer was out (it changes nothing): they
#: begin so, and name what is out before these.
_ALL_OUT = ("all of the ", " is out: the control ")


def all_out_words(what: str, drip: bool) -> str:
    """A stop when all of ``what`` (``drip-feed of O5000.nc``) was out already, in words:
    the control runs (or stores) the rest; :func:`says_all_out` knows these words again."""
    rest = "runs the rest: stop it on the control (FEED HOLD, RESET)" if drip else "stores it"
    return f"{_ALL_OUT[0]}{what}{_ALL_OUT[1]}{rest}"


def says_all_out(text: str) -> bool:
    """Whether ``text`` (a log line without its time) is :func:`all_out_words`'."""
    return text.startswith(_ALL_OUT[0]) and _ALL_OUT[1] in text


def offline_words(name: str, e: Exception, retry_s: float | None) -> str:
    """Why machine ``name`` is offline, naming it: ``a: offline: cannot connect to ...``;
    with ``retry_s`` (a server that tries its link again), how often it is tried."""
    text = str(e)
    text = text[len(name) + 2 :] if text.startswith(f"{name}: ") else text
    if retry_s is None:  # a one-shot command: nothing tries again
        return f"{name}: offline: {text}"
    return f"{name}: offline: {text} (its link is tried again every {retry_s:g} s)"


def online_words(name: str, url: str) -> str:
    """Machine ``name`` back from offline, in the words of :func:`offline_words` (the log's
    line beside its ``offline`` one): ``a: online: its link socket://... is open again``."""
    return f"{name}: online: its link {url} is open again"


def started_words(program: str, drip: bool, chars: int) -> str:
    """A transfer by hand taken, in the words of its end's log line (``O1234.nc: read in,
    4691 characters of program in 5.3 s ...``): ``O1234.nc: read-in by hand, 4691
    characters of program: waiting for read: press READ on the control, in EDIT mode``."""
    what = "drip-feed" if drip else "read-in"
    return (
        f"{program}: {what} by hand, {chars} characters of program: waiting for read: "
        f"{START_READ[drip]}"
    )
