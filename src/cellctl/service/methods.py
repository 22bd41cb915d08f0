"""The control API's methods: JSON-RPC 2.0 names, their parameters, what they answer.

One :class:`Dispatcher` serves every transport (the WebSocket server, and in-process for the
CLI and the console without a controller)::

    dispatcher = Dispatcher(AttachedCell(controller))
    status = await dispatcher.call("cell.status", {})
    await dispatcher.call("robot.status", {"machine": "robot"})

Parameters (models in :mod:`cellctl.service.params`) are validated (unknown keys refused)
and every failure is a typed :class:`~cellctl.errors.CellctlError` with the CLI's message;
:func:`error_object` turns it into a JSON-RPC error whose ``data`` names the type, so a
client raises the same error.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Iterator, Mapping
from functools import cached_property
from typing import Any

from pydantic import ValidationError

from cellctl import __version__
from cellctl.errors import (
    AccessDenied,
    CellctlError,
    DeviceError,
    ProtocolError,
    UsageError,
    exit_code,
    with_article,
)
from cellctl.kinds import registry
from cellctl.service import operator, orderdue
from cellctl.service.access import CellAccess
from cellctl.service.audit import AuditLog
from cellctl.service.functions import (
    InvalidParams,
    Progress,
    describe,
    function,
    functions,
    kind_menu,
)

# Declared in params.py; the `X as X` ones are re-exported (plug-ins and tests import them here).
from cellctl.service.params import (
    AlarmParams,
    AlarmsParams,
    AuditParams,
    EstopParams,
    Handler,
    HistoryParams,
    IdParams,
    MachineParams,
    NoParams,
    OrdersParams,
    PartsParams,
    PreviewParams,
    ReleaseParams,
    ScrapParams,
    ShelveParams,
    ShiftParams,
    StepsParams,
    SubmitParams,
    TrafficParams,
)
from cellctl.service.params import MachineCallParams as MachineCallParams
from cellctl.service.params import Method as Method
from cellctl.service.params import P as P
from cellctl.service.planning import PlanParams, plan_run
from cellctl.service.rpc import APP_ERROR_BASE as APP_ERROR_BASE
from cellctl.service.rpc import CALLER, caller_label, caller_name, login_name
from cellctl.service.rpc import INTERNAL_ERROR as INTERNAL_ERROR
from cellctl.service.rpc import INVALID_PARAMS as INVALID_PARAMS
from cellctl.service.rpc import INVALID_REQUEST as INVALID_REQUEST
from cellctl.service.rpc import METHOD_NOT_FOUND as METHOD_NOT_FOUND
from cellctl.service.rpc import PARSE_ERROR as PARSE_ERROR
from cellctl.service.rpc import Caller as Caller
from cellctl.service.rpc import error_from_object as error_from_object
from cellctl.service.token import role_allows
from cellctl.service.trail import CallTrail, Started

#: The most requests one JSON-RPC batch may hold.
MAX_BATCH = 100
#: What the audit trail says of an acting call cut short (its task cancelled: the server
#: stopping, aborted by a second Ctrl-C).
CANCELLED = "cancelled"

log = logging.getLogger(__name__)


async def _info(access: CellAccess, p: NoParams, progress: Progress | None) -> Any:
    methods = [*METHODS.values(), *access.methods().values()]
    caller = CALLER.get() or local_caller()
    return {
        "version": __version__,
        "mode": access.mode,
        "directory": str(access.directory),
        "methods": {m.name: m.doc for m in methods},
        # Who asks, and the role each method needs: a client offers what its caller may do
        # (the console refuses a function before it takes a machine out of service for it).
        "caller": {"who": caller.who, "role": caller.role},
        "roles": {m.name: m.role for m in methods},
    }


async def _status(access: CellAccess, p: NoParams, progress: Progress | None) -> Any:
    return access.snapshot()


async def _schema(access: CellAccess, p: NoParams, progress: Progress | None) -> Any:
    from cellctl.service.status import status_schema

    return status_schema()


async def _pause(access: CellAccess, p: NoParams, progress: Progress | None) -> Any:
    access.controller().pause(by=caller_label())
    return {"message": "paused: steps in flight finish, no new step starts"}


async def _resume(access: CellAccess, p: NoParams, progress: Progress | None) -> Any:
    return {"message": access.controller().resume(by=caller_label())}


async def _estop(access: CellAccess, p: EstopParams, progress: Progress | None) -> Any:
    return {"message": await access.controller().emergency_stop(p.reason, by=caller_label())}


async def _submit(access: CellAccess, p: SubmitParams, progress: Progress | None) -> Any:
    from cellctl.service.machines import load_cell_file

    parts = load_cell_file(access.directory).get("parts")
    types = list(parts) if isinstance(parts, dict) else None
    operator.check_part_type(types, p.part_type)  # before the mailbox file is made
    result = orderdue.submit_order(access.mailbox(), types, p)  # p.due read with the params
    access.poke()
    return result


async def _orders(access: CellAccess, p: OrdersParams, progress: Progress | None) -> Any:
    from cellctl.service.layout import cell_config

    try:
        config = cell_config(access)  # for what blocks an order
    except UsageError:
        config = None
    return orderdue.list_orders(access.mailbox(), access.journal(), p.states, config)


async def _cancel(access: CellAccess, p: IdParams, progress: Progress | None) -> Any:
    result = operator.cancel_order(access.mailbox(), access.journal(), p.id)
    access.poke()
    return result


def _journal(access: CellAccess) -> Any:
    journal = access.journal()
    if journal is None:
        raise UsageError(f"no journal in {access.directory}: the cell has not run yet")
    return journal


async def _alarms(access: CellAccess, p: AlarmsParams, progress: Progress | None) -> Any:
    journal = access.journal()
    if journal is None:
        return []
    found = journal.alarms() if p.all else journal.active_alarms()
    return [operator.as_dict(a) for a in found]


async def _clear(access: CellAccess, p: AlarmParams, progress: Progress | None) -> Any:
    result = operator.clear_alarm(_journal(access), access.mailbox(), p.id, by=caller_name())
    access.poke()
    return result


async def _ack(access: CellAccess, p: AlarmParams, progress: Progress | None) -> Any:
    result = operator.ack_alarm(_journal(access), p.id, by=caller_name())
    access.poke()
    return result


async def _shelve(access: CellAccess, p: ShelveParams, progress: Progress | None) -> Any:
    result = operator.shelve_alarm(_journal(access), p.id, p.seconds, by=caller_name())
    access.poke()
    return result


async def _unshelve(access: CellAccess, p: AlarmParams, progress: Progress | None) -> Any:
    result = operator.unshelve_alarm(_journal(access), p.id, by=caller_name())
    access.poke()
    return result


async def _history(access: CellAccess, p: HistoryParams, progress: Progress | None) -> Any:
    journal = access.journal()
    if journal is None:
        return []
    found = journal.alarm_history(
        since=p.since, machine=p.machine, priority=p.priority, limit=p.limit
    )
    return [operator.as_dict(a) for a in found]


async def _parts(access: CellAccess, p: PartsParams, progress: Progress | None) -> Any:
    journal = access.journal()
    if journal is None:
        return []
    return [operator.part_entry(journal, x) for x in journal.parts(p.statuses or None, p.order)]


async def _release(access: CellAccess, p: ReleaseParams, progress: Progress | None) -> Any:
    result = operator.release_part(
        _journal(access), access.mailbox(), p.id, redo=p.redo, location=p.at, places=access.places()
    )
    access.poke()
    return result


async def _scrap(access: CellAccess, p: ScrapParams, progress: Progress | None) -> Any:
    result = operator.scrap_part(
        _journal(access), access.mailbox(), p.id, p.reason, taken_out=p.taken_out
    )
    access.poke()
    return result


async def _machines(access: CellAccess, p: NoParams, progress: Progress | None) -> Any:
    return access.snapshot()["machines"]


async def _out(access: CellAccess, p: MachineParams, progress: Progress | None) -> Any:
    access.require_machine(p.machine)
    message = await access.controller().set_service(p.machine, False, p.reason)
    return {"message": message}


async def _in(access: CellAccess, p: MachineParams, progress: Progress | None) -> Any:
    access.require_machine(p.machine)
    message = await access.controller().set_service(p.machine, True, p.reason)
    return {"message": message}


async def _plc_status(access: CellAccess, p: NoParams, progress: Progress | None) -> Any:
    from cellctl.protocol.plc import SIGNALS

    plc = access.controller().plc  # the controller's own link: it holds the PLC
    if plc is None:
        raise UsageError("the controller has not connected to the PLC yet: ask again shortly")
    read = {"inputs": await plc.read_inputs(), "coils": await plc.read_coils()}
    addresses = {"inputs": plc.map.inputs, "coils": plc.map.coils}
    return {
        "url": plc.url,
        "unit": plc.map.unit,
        **{
            kind: {
                name: {
                    "level": level,
                    "address": addresses[kind][name],
                    "meaning": SIGNALS[name].meaning,
                }
                for name, level in levels.items()
            }
            for kind, levels in read.items()
        },
    }


async def _traffic(access: CellAccess, p: TrafficParams, progress: Progress | None) -> Any:
    access.require_machine(p.machine)
    return access.traffic(p.machine, p.limit)


async def _layout(access: CellAccess, p: NoParams, progress: Progress | None) -> Any:
    from cellctl.service.layout import cell_layout

    return cell_layout(access)


async def _steps(access: CellAccess, p: StepsParams, progress: Progress | None) -> Any:
    from cellctl.service.layout import journal_steps

    return journal_steps(access, p.since)


async def _shift(access: CellAccess, p: ShiftParams, progress: Progress | None) -> Any:
    from cellctl.service.layout import shift_figures

    return shift_figures(access, p.since, p.until)


async def _preview(access: CellAccess, p: PreviewParams, progress: Progress | None) -> Any:
    from cellctl.service.layout import program_preview

    return program_preview(access, p.machine, p.program)


async def _audit(access: CellAccess, p: AuditParams, progress: Progress | None) -> Any:
    if access.journal() is None:
        return []

    def read() -> list[dict[str, Any]]:
        with AuditLog(access.directory) as log:
            return [e.as_dict() for e in log.entries(since=p.since, who=p.who, limit=p.limit)]

    return await asyncio.to_thread(read)  # off the loop, as the entries are written


def _machine_handler(family: str, function_name: str) -> Handler:
    """The handler of ``FAMILY.NAME``: it runs the function of the named machine's own kind
    (two mill kinds may have different menus; one without the function refuses the call)."""

    async def handler(access: CellAccess, p: MachineCallParams, progress: Progress | None) -> Any:
        name = _machine_name(access, family, p.machine)
        fn = function(family, function_name, access.machine_kinds().get(name))
        prepared = fn.check(dict(p.model_extra or {}))  # refused here: no byte went out
        async with access.driver(name, observe=fn.observes) as driver:
            result = await fn.run(driver, prepared, progress)
        note = getattr(access, "note", None)
        if note is not None:
            note(f"{name}: {fn.label}: {result.get('message', '')}")
        return {"machine": name, **result}

    return handler


def _machine_name(access: CellAccess, family: str, name: str | None) -> str:
    machines = access.machines()
    mine = [n for n, fam in machines.items() if fam == family]
    if name is None:
        if len(mine) == 1:
            return mine[0]
        raise UsageError(f"which {family}? (known: {', '.join(mine) or 'none'})")
    if name not in machines:
        raise UsageError(f"unknown {family} {name!r} (known: {', '.join(mine) or 'none'})")
    if machines[name] != family:
        raise UsageError(f"machine {name!r} is {with_article(machines[name])}, not a {family}")
    return name


_TABLE: list[Method] = [
    Method(
        "server.info",
        NoParams,
        _info,
        "Version, mode, the methods served, the caller's role and each method's.",
        False,
    ),
    Method("cell.status", NoParams, _status, "Machines, orders, parts, alarms, events.", False),
    Method("cell.schema", NoParams, _schema, "JSON Schema of the status and its updates.", False),
    Method("cell.pause", NoParams, _pause, "Finish the steps in flight, start no new one.", True),
    Method("cell.resume", NoParams, _resume, "Start dispatching again.", True),
    Method("cell.estop", EstopParams, _estop, "Stop the robot, halt the mills, alarm.", True),
    Method("orders.submit", SubmitParams, _submit, "Post an order, due by a time if given.", True),
    Method("orders.list", OrdersParams, _orders, "Orders: parts' statuses, due, late.", False),
    Method("orders.cancel", IdParams, _cancel, "Cancel an order that has not started.", True),
    Method("alarms.list", AlarmsParams, _alarms, "Active alarms (all with all=true).", False),
    Method("alarms.clear", AlarmParams, _clear, "Clear (end) an alarm.", True),
    Method("alarms.ack", AlarmParams, _ack, "Acknowledge an alarm (it stays open).", True),
    Method("alarms.shelve", ShelveParams, _shelve, "Shelve an alarm for seconds (<= 8 h).", True),
    Method("alarms.unshelve", AlarmParams, _unshelve, "Unshelve an alarm: shown again now.", True),
    Method("alarms.history", HistoryParams, _history, "Alarms by time, machine, priority.", False),
    Method(
        "parts.list", PartsParams, _parts, "Parts, by status or order (held: may_be_in).", False
    ),
    Method("parts.release", ReleaseParams, _release, "Release a held part.", True),
    Method(
        "parts.scrap",
        ScrapParams,
        _scrap,
        "Scrap a held or waiting part; one that may be in a machine only taken_out by hand.",
        True,
    ),
    Method("machines.list", NoParams, _machines, "Every machine's state and service.", False),
    Method(
        "plc.status",
        NoParams,
        _plc_status,
        "The PLC's inputs and coils, read now through the controller (it holds the PLC).",
        False,
    ),
    Method("machines.out_of_service", MachineParams, _out, "Out of automatic service.", True),
    Method("machines.return_to_service", MachineParams, _in, "Back in automatic service.", True),
    Method("traffic.tail", TrafficParams, _traffic, "A machine's last bytes both ways.", False),
    Method("cell.layout", NoParams, _layout, "Machines, places and part routes.", False),
    Method("steps.list", StepsParams, _steps, "Journal steps started since a time.", False),
    Method("report.shift", ShiftParams, _shift, "A shift's OEE, parts, alarms, downtime.", False),
    Method(
        "programs.preview", PreviewParams, _preview, "Toolpath SVG of a route's program.", False
    ),
    Method("audit.list", AuditParams, _audit, "Who did what, when, and its result.", False),
    # A viewer's: it acts on nothing, it plays the cell's state on a copy (service/planning).
    Method(
        "plan.run",
        PlanParams,
        plan_run,
        "Play the cell ahead on a copy: a plan.",
        False,
        abandoned=True,
    ),
]


#: Reads that touch no machine (their answer is all they make): a call of one ends when its
#: client goes away, or when the server stops. ``plc.status`` asks the PLC on its link, and
#: a machine's own functions talk to it: those run to their end, as acting calls do.
_ENDS_WITH_CLIENT = frozenset(m.name for m in _TABLE if not m.acts and m.name != "plc.status")


def _machine_methods() -> list[Method]:
    """Each machine function of the installed kinds, as FAMILY.NAME."""
    return [
        Method(
            f"{fn.family}.{fn.name}",
            MachineCallParams,
            _machine_handler(fn.family, fn.name),
            f"{fn.label}: {fn.doc}"
            + (" Also in automatic service." if fn.observes else " Out of automatic service only."),
            not fn.observes,
            # By hand a machine is an engineer's; what only observes it, anyone's.
            role="viewer" if fn.observes else "engineer",
        )
        for fn in functions()
    ]


class _Methods(Mapping[str, Method]):
    """The methods by name: the cell's own, then the machines' functions. Those are read
    from the installed kinds on first need, so a call of the cell's own (``parts.list``
    from the command line) imports no kind's package."""

    def __init__(self, own: list[Method]) -> None:
        self._own = {m.name: m for m in own}

    @cached_property
    def _all(self) -> dict[str, Method]:
        return {**self._own, **{m.name: m for m in _machine_methods()}}

    def __getitem__(self, name: str) -> Method:
        own = self._own.get(name)
        return own if own is not None else self._all[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._all)

    def __len__(self) -> int:
        return len(self._all)


METHODS: Mapping[str, Method] = _Methods(_TABLE)


def reference_table() -> str:
    """The methods as a Markdown table (docs/api.md holds exactly this): a plug-in kind's
    functions are its own docs', so the table stays the same wherever it is rendered."""
    shipped = {
        f"{fn.family}.{fn.name}"
        for k in registry.kinds()
        if k.origin is None or k.origin.module.startswith("cellctl.")
        for fn in kind_menu(k.name)
    }
    rows = [
        "| method | parameters (? optional) | what it does | acts | role |",
        "|---|---|---|---|---|",
    ]
    for m in METHODS.values():
        fields = dict(m.params.model_fields)
        if m.params is MachineCallParams:
            if m.name not in shipped:
                continue
            family, name = m.name.split(".")
            fields.update(function(family, name).params.model_fields)
        names = ", ".join(k + ("" if f.is_required() else "?") for k, f in fields.items())
        acts = "yes" if m.acts else "no"
        rows.append(f"| `{m.name}` | {names or '-'} | {m.doc} | {acts} | {m.role} |")
    return "\n".join(rows) + "\n"


class MethodNotFound(UsageError):
    """No such method."""


class RoleRefused(AccessDenied):
    """The caller's role may not call the method; ``needs`` is the role it lacks."""

    def __init__(self, message: str, needs: str) -> None:
        super().__init__(message)
        self.needs = needs


def local_caller() -> Caller:
    """The user at this computer, calling in-process: they hold the cell's files already."""
    return Caller(f"local:{login_name()}", "engineer")


class Dispatcher:
    """Calls methods on one cell (see module docstring). Each call is checked against the
    caller's role, and every acting call (and every refused one) goes to the audit trail
    when the directory is a cell: an acting call as it begins (``running``), its entry then
    given its end (:mod:`cellctl.service.trail`)."""

    def __init__(self, access: CellAccess) -> None:
        self.access = access
        self.trail = CallTrail(access.directory)

    async def call(
        self,
        method: str,
        params: Any = None,
        progress: Progress | None = None,
        *,
        caller: Caller | None = None,
    ) -> Any:
        """Run ``method`` with ``params`` (a dict or None) for ``caller`` (the local user
        when None); typed errors on failure (:class:`RoleRefused` for a role too low)."""
        caller = caller or local_caller()
        entry = self._entry(method)
        started: Started | None = None
        try:
            if entry is None:
                more = f"… (cut from {len(method)} characters)" if len(method) > 64 else ""
                raise MethodNotFound(f"no method {method[:64]!r}{more} (server.info lists them)")
            if not role_allows(caller.role, entry.role):
                name = caller.who.partition(":")[2] or caller.who
                raise RoleRefused(
                    f"{name} is {with_article(caller.role)}: {method} needs the {entry.role} role",
                    entry.role,
                )
            if entry.acts:  # on record from now on, a crash meanwhile included
                started = self.trail.begin(caller.who, method, params)
            called = CALLER.set(caller)
            try:
                result = await self._run(entry, method, params, progress)
            finally:
                CALLER.reset(called)
        except asyncio.CancelledError:
            # Cut short (the server stopping, a second Ctrl-C): an acting call is audited
            # so, and said, before the cancellation goes on.
            if started is not None:
                log.warning("%s by %s was cut short before its end (cancelled)", method, caller.who)
                with contextlib.suppress(asyncio.CancelledError):
                    # Shielded: cancelled again, the entry is still written (in its thread).
                    await asyncio.shield(self.trail.end(started, CANCELLED))
            raise
        except Exception as e:
            text = str(e) or type(e).__name__
            if started is not None:
                await self.trail.end(started, text)
            elif isinstance(e, RoleRefused):  # decided at once: one entry, counted if repeated
                await self.trail.record(caller.who, method, params, text, collapse=True)
            raise
        if started is not None:
            await self.trail.end(started, "ok")
        return result

    def _entry(self, method: str) -> Method | None:
        """``method``'s entry: the common table's, else the access's own (None: no such)."""
        return METHODS.get(method) or self.access.methods().get(method)

    def abandoned(self, method: str) -> bool:
        """True if a call of ``method`` ends when its client goes away, or the server stops:
        one declared so (:class:`Method`), or a read of the cell's that touches no machine.
        Every other call (acting, or talking to a machine) runs to its end."""
        entry = self._entry(method)
        return entry is not None and (entry.abandoned or method in _ENDS_WITH_CLIENT)

    async def _run(self, entry: Method, method: str, params: Any, progress: Progress | None) -> Any:
        params = {} if params is None else params
        if not isinstance(params, dict):
            raise InvalidParams(f"{method}: params: parameters must be an object with names")
        try:
            checked = entry.params.model_validate(params)
        except ValidationError as e:
            raise InvalidParams(f"{method}: {describe(e)}") from None
        return await entry.handler(self.access, checked, progress)

    def close(self) -> None:
        self.trail.close()


def error_object(error: BaseException) -> dict[str, Any]:
    """The JSON-RPC error object for ``error`` (a typed one keeps its type and message)."""
    if isinstance(error, MethodNotFound):
        return {"code": METHOD_NOT_FOUND, "message": str(error), "data": _data(error, 2)}
    if isinstance(error, InvalidParams):  # a client raises it as the UsageError it is
        return {"code": INVALID_PARAMS, "message": str(error), "data": _data(error, 2)}
    if isinstance(error, CellctlError):
        code = exit_code(error)
        return {"code": APP_ERROR_BASE - code, "message": str(error), "data": _data(error, code)}
    return {"code": INTERNAL_ERROR, "message": f"internal error: {type(error).__name__}: {error}"}


def _data(error: CellctlError, code: int) -> dict[str, Any]:
    kind = "UsageError" if isinstance(error, InvalidParams) else None
    kind = "AccessDenied" if isinstance(error, RoleRefused) else kind
    data: dict[str, Any] = {"type": kind or type(error).__name__, "exit_code": code}
    if isinstance(error, RoleRefused):
        data["role"] = error.needs
    if isinstance(error, DeviceError):
        data.update(device_code=error.code, device_message=error.message, detail=error.detail)
    if isinstance(error, ProtocolError):
        data["raw"] = error.raw.hex()
    return data
