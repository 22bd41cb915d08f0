"""The DNC server as the control API sees it: the service's own server and status, on the
shop directory instead of a cell::

    server = DncServer(load_shop(Path("SHOP")))
    api = ApiServer(DncAccess(server), Path("SHOP"))    # SHOP/api.sock, SHOP/api-token (0600)

``cell.status`` (and ``GET /api/status``, the console, the dashboard) shows each DNC machine
as a mill of kind ``iso-cnc``: its condition (idle, busy, offline), its state in words
(``drip-feeding O1234, stalled 0.4 s``) and its progress in characters (rate, time left).
Methods of its own (:meth:`DncAccess.methods`):

- ``dnc.send`` ``{machine, program, text?, drip?}``: send a program by hand (``text``: its
  text; else ``program`` is an O-number or file name of ``SHOP/<machine>/programs``); the
  control starts the read. Progress is pushed (``notify_progress``) as characters go. A busy
  machine is refused at once (MachineInUse); ``ticket`` names it for ``dnc.stop``. A transfer
  stopped before its end (``dnc.stop``, the server stopping) is an error saying where it
  ended, after a last progress whose ``stopped`` field has the same words (``phase``
  ``ended``): a client tells a stop from a failure by that field.
- ``dnc.receive`` ``{machine, timeout?}``: take what the control punches; kept as received
  (the wait ends when its WebSocket client goes).
- ``dnc.stop`` ``{machine, ticket?}``: end the read-in or drip-feed in flight the clean way
  (whoever started it; with ``ticket``, only the one sent with it), or drop the request
  waiting for the control's read.
- ``dnc.log`` ``{machine, last?}``: the last lines of the machine's log.
- ``machines.functions``: what an operator may do to each machine (:data:`FUNCTIONS`), for a
  client that builds its menus from the server (the console).

Each but ``dnc.stop`` waits for the machine's turn: a punch or a request's answer in flight
finishes first. ``traffic.tail`` shows each machine's last bytes both ways (kept from the
first ``traffic.tail`` on, while clients keep asking).
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import AsyncIterator, Mapping
from pathlib import Path
from typing import Any

from pydantic import Field

from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.kinds import Condition
from cellctl.kinds.iso_cnc.dnc.config import KIND
from cellctl.kinds.iso_cnc.dnc.server import PUNCH_S, STOP_S, TRANSFER_S, DncServer
from cellctl.kinds.iso_cnc.dnc.status import (
    Activity,
    MachineStatus,
    TransferStopped,
    WatchedTraffic,
    state_words,
    stopped_progress,
)
from cellctl.kinds.iso_cnc.dnc.store import check_program_number, read_program_file
from cellctl.kinds.iso_cnc.tape import not_iso_code
from cellctl.kinds.menu import MAX_PROGRAM_CHARS, PrintableText, Progress
from cellctl.mailbox import Mailbox
from cellctl.service.access import CellAccess, traffic_rows
from cellctl.service.methods import Method, P
from cellctl.service.status import (
    CellInfo,
    CellMode,
    CellStatus,
    ErrorInfo,
    EventInfo,
    ProgressInfo,
)
from cellctl.service.status import MachineStatus as ApiMachine

CONDITIONS = {
    Activity.IDLE: Condition.IDLE,
    Activity.WAITING: Condition.BUSY,
    Activity.READING: Condition.BUSY,
    Activity.DRIP_FEEDING: Condition.BUSY,
    Activity.PUNCHING: Condition.BUSY,
    Activity.AWAITING_PUNCH: Condition.IDLE,
    Activity.OFFLINE: Condition.OFFLINE,
}


class SendParams(P):
    machine: PrintableText = Field(min_length=1, max_length=64)
    program: PrintableText = Field(min_length=1, max_length=500)
    text: str | None = Field(default=None, max_length=MAX_PROGRAM_CHARS)
    drip: bool = False
    ticket: PrintableText | None = Field(default=None, min_length=1, max_length=64)
    """The caller's own name for this transfer: ``dnc.stop`` with it stops this one only."""


class ReceiveParams(P):
    machine: PrintableText = Field(min_length=1, max_length=64)
    timeout: float = Field(default=600.0, gt=0, le=PUNCH_S)


class LogParams(P):
    machine: PrintableText = Field(min_length=1, max_length=64)
    last: int = Field(default=50, ge=1, le=10_000)


class StopParams(P):
    machine: PrintableText = Field(min_length=1, max_length=64)
    ticket: PrintableText | None = Field(default=None, min_length=1, max_length=64)
    """Stop only the transfer sent with this ticket (a client stopping its own)."""


class NoParams(P):
    pass


#: Seconds the console waits for a punch (RECEIVE PUNCH).
RECEIVE_S = 600.0
#: Seconds a client waits for an answer beyond the method's own deadline.
CALL_MARGIN_S = 30.0
#: What an operator may do to a DNC machine, as ``machines.functions`` serves it: a menu key
#: and label, the method and its fixed parameters, what the client asks the operator for
#: (``program``: a program file, sent as ``program`` and ``text``), a question to confirm.
FUNCTIONS: tuple[dict[str, Any], ...] = (
    {
        "key": "1",
        "label": "READ IN",
        "method": "dnc.send",
        "params": {"drip": False},
        "asks": ["program"],
        "doc": "Into the control's memory: press READ on the control (EDIT mode).",
        "timeout_s": TRANSFER_S + CALL_MARGIN_S,
    },
    {
        "key": "2",
        "label": "DRIP FEED",
        "method": "dnc.send",
        "params": {"drip": True},
        "asks": ["program"],
        "doc": "The control runs it as it arrives: CYCLE START in RMT (DNC) mode.",
        "timeout_s": TRANSFER_S + CALL_MARGIN_S,
    },
    {
        "key": "3",
        "label": "RECEIVE PUNCH",
        "method": "dnc.receive",
        "params": {"timeout": RECEIVE_S},
        "asks": [],
        "doc": "Keep what the control punches next: press PUNCH on the control.",
        "timeout_s": RECEIVE_S + CALL_MARGIN_S,
    },
    {
        "key": "4",
        "label": "STOP TRANSFER",
        "method": "dnc.stop",
        "params": {},
        "asks": [],
        "confirm": "Stop the transfer in flight (or drop the request waiting for a read)? "
        "A read under way ends with the rest of its block and %: the control leaves the read.",
        "doc": "Stop the read-in or drip-feed in flight.",
        "timeout_s": STOP_S + CALL_MARGIN_S,
    },
    {
        "key": "5",
        "label": "LOG",
        "method": "dnc.log",
        "params": {"last": 5},
        "asks": [],
        "doc": "The machine's last log lines.",
    },
)


def _progress(s: MachineStatus) -> ProgressInfo | None:
    if s.activity not in (Activity.READING, Activity.DRIP_FEEDING, Activity.PUNCHING):
        return None
    # A punch's size is not known until its DC4: its total stays 0 (unknown), never the
    # characters so far, which would show a punch under way as done (100%).
    total = 0 if s.activity is Activity.PUNCHING else max(s.chars_total, s.chars_done)
    return ProgressInfo(
        phase=s.phase or s.activity.value,
        done=s.chars_done,
        total=total,
        unit="chars",
        fraction=s.chars_done / total if total else 0.0,
        program=s.program,
        since=s.since,
        rate_per_s=s.chars_per_s,
        time_left_s=s.eta_s if s.eta_s is not None and math.isfinite(s.eta_s) else None,
        stall_s=s.stall_s if s.activity is Activity.DRIP_FEEDING else None,
    )


class DncAccess(CellAccess):
    """The control API's view of a running DNC server (see module docstring)."""

    mode = "attached"

    def __init__(self, server: DncServer) -> None:
        self.server = server
        self.directory = server.config.root
        self.events: list[tuple[float, str]] = []

    def journal(self) -> None:
        return None

    def mailbox(self) -> Mailbox:
        raise UsageError("a DNC server takes no orders: it feeds its machines their programs")

    def machines(self) -> dict[str, str]:
        return dict.fromkeys(self.server.lines, "mill")

    def machine_kinds(self) -> dict[str, str]:
        return dict.fromkeys(self.server.lines, KIND)

    @contextlib.asynccontextmanager
    async def driver(self, name: str, *, observe: bool = False) -> AsyncIterator[Any]:
        line = self.server.line(name)
        async with line.turn:
            yield line.driver

    def status(self) -> CellStatus:
        now = current_clock().now()
        elapsed = max(now - self.server.started, 1e-9)
        machines = {}
        for name, s in self.server.status().items():
            busy = now - s.since if s.activity is not Activity.IDLE and s.since else 0.0
            machines[name] = ApiMachine(
                name=name,
                kind=KIND,
                family="mill",
                condition=CONDITIONS[s.activity],
                state=state_words(s),
                progress=_progress(s),
                error=ErrorInfo(text=s.error) if s.error else None,
                failures=s.failures,
                busy_s=busy,
                utilization=min(1.0, busy / elapsed),
                in_service=True,
                out_reason="",
                manual=True,
            )
        cell = CellInfo(
            name=self._name(),
            directory=str(self.directory),
            access="attached",
            mode=CellMode.RUNNING,
            paused=False,
            started_at=self.server.started,
            pid=os.getpid(),
            time=now,
        )
        lines = [(t, x) for line in self.server.lines.values() for t, x in line.events]
        events = [EventInfo(time=t, text=x) for t, x in sorted(lines)[-30:]]
        return CellStatus(
            cell=cell, machines=machines, orders=[], parts=[], alarms=[], events=events
        )

    def layout(self) -> dict[str, Any]:
        """The shop as the dashboard draws it: its machines, no robot, no part types."""
        names = list(self.server.lines)
        return {
            "name": self._name(),
            "robot": None,
            "mills": names,
            "places": names,
            "machines": [
                {"name": n, "kind": KIND, "family": "mill", "role": "mill"} for n in names
            ],
            "part_types": {},
        }

    def _name(self) -> str:
        return f"DNC {Path(self.directory).absolute().name}"

    def traffic(self, name: str, limit: int) -> list[dict[str, Any]]:
        line = self.server.line(name)
        if isinstance(line.trace, WatchedTraffic):
            line.trace.watch()  # kept from now on, while someone looks
        return [] if line.trace is None else traffic_rows(line.trace, name, limit)

    def methods(self) -> Mapping[str, Any]:
        return METHODS


async def _send(access: CellAccess, p: SendParams, progress: Progress | None) -> Any:
    assert isinstance(access, DncAccess)
    line = access.server.line(p.machine)
    if p.text is not None:
        # Its bytes as a file's (UTF-8): a text that is not ASCII is refused in the words of
        # `cellctl dnc send FILE` for that file (byte and value), whoever sent it.
        name, data = p.program, p.text.encode("utf-8", "surrogatepass")
        refusal = not_iso_code(name, data)
        if refusal is not None:
            raise UsageError(refusal)
    else:
        # A path is this host's: a client names a program of the shop, or sends its text.
        digits = line.config.options.o_digits
        path = line.store.resolve(p.machine, p.program, digits, shop_only=True)
        name, data = path.name, read_program_file(path)
    check_program_number(name, data)
    what = f"{'drip-feed' if p.drip else 'read-in'} of {name}"
    # a busy machine: refused at once, naming what it does
    with line.claim(what, p.ticket):
        async with line.turn:
            try:
                result = await line.send(
                    name,
                    data,
                    drip=p.drip,
                    progress=progress,
                    ticket=p.ticket,
                    by_hand=True,
                )
            except TransferStopped as e:
                if progress is not None:  # a field its caller reads: stopped, not failed
                    progress(stopped_progress(line.status, str(e)))
                raise
    return {"machine": p.machine, **result}


async def _receive(access: CellAccess, p: ReceiveParams, progress: Progress | None) -> Any:
    assert isinstance(access, DncAccess)
    line = access.server.line(p.machine)
    line.require_link("nothing can be punched to the server")  # said before any prompt
    if progress is not None:  # the caller may now ask the operator to press PUNCH
        progress({"phase": "waiting", "chars_sent": 0, "chars_total": 0})
    programs = await line.wait_punch(p.timeout)
    message = "; ".join(_punched(x) for x in programs) or "nothing punched"
    return {"machine": p.machine, "message": message, "programs": programs}


def _punched(item: dict[str, Any]) -> str:
    """One program of a punch, in words (what became of it)."""
    if "refused" in item:
        return f"refused: {item['refused']}"
    if "request" in item:
        return f"request: {item['request']}"
    kept = Path(str(item["kept"])).name
    return f"received O{item['program']:04d} ({item.get('chars', 0)} chars) as {kept}"


async def _stop(access: CellAccess, p: StopParams, progress: Progress | None) -> Any:
    assert isinstance(access, DncAccess)
    why = "stopped by its sender" if p.ticket else "stopped by hand"
    line = access.server.line(p.machine)
    message = await line.stop(ticket=p.ticket, why=why)
    # False when nothing was stopped: no transfer, or all of it was out already (a drip-feed
    # the control runs to its end): the transfer's own end stands.
    return {"machine": p.machine, "message": message, "stopped": bool(line.stopping)}


async def _functions(access: CellAccess, p: NoParams, progress: Progress | None) -> Any:
    assert isinstance(access, DncAccess)
    return {name: list(FUNCTIONS) for name in access.server.lines}


async def _log(access: CellAccess, p: LogParams, progress: Progress | None) -> Any:
    assert isinstance(access, DncAccess)
    line = access.server.line(p.machine)
    lines = line.store.log_lines(p.machine, p.last)
    message = f"the last {len(lines)} lines of its log" if lines else "its log is empty"
    return {"machine": p.machine, "message": message, "lines": lines}


METHODS: dict[str, Method] = {
    m.name: m
    for m in [
        Method("dnc.send", SendParams, _send, "Send (or drip-feed) a program by hand.", True),
        # Its wait ends with its client (the machine's task takes the punch, whoever waits):
        # a `dnc receive` killed leaves no "waiting for punch" behind until its timeout.
        Method(
            "dnc.receive",
            ReceiveParams,
            _receive,
            "Take what the control punches.",
            True,
            abandoned=True,
        ),
        Method("dnc.stop", StopParams, _stop, "Stop the transfer in flight.", True),
        Method("dnc.log", LogParams, _log, "The last lines of a machine's log.", False),
        Method(
            "machines.functions",
            NoParams,
            _functions,
            "What an operator may do to each machine (menus of a client).",
            False,
        ),
    ]
}
