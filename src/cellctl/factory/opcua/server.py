"""The OPC UA server that ``cellctl run`` starts when cell.toml has ``[opcua] listen``.

::

    server = OpcuaServer(AttachedCell(controller), config.opcua, log=controller.log)
    await server.start()          # the certificate is made at the first run
    ...                           # pushed every change by the controller's listeners
    await server.close()

It reads the cell through the control API's own methods (``cell.status``, ``steps.list``,
``parts.list``) and acts through them (``orders.submit``, ``alarms.clear``), so it can do
nothing the API cannot, and a refusal comes back in the same words: as a Bad status code with
the words in the result's diagnostic information (``AdditionalInfo``). Endpoints are
Basic256Sha256 with Sign or SignAndEncrypt only; users log in with a name and password; an
anonymous session, when allowed, can read, browse and subscribe, never call or write.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import re
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import quote

from asyncua import ua
from asyncua.common.node import Node
from asyncua.server.event_generator import EventGenerator
from asyncua.server.server import Server
from asyncua.ua.object_ids import ObjectIds
from asyncua.ua.status_codes import StatusCodes

from cellctl.cell.config import OpcuaTable
from cellctl.clock import current_clock
from cellctl.errors import CellctlError, DeviceError, UsageError
from cellctl.factory.opcua.certs import ensure_certificate, thumbprint
from cellctl.factory.opcua.conditions import (
    CLEARED_SEVERITY,
    SEVERITY,
    AlarmConditions,
    bind_condition_methods,
)
from cellctl.factory.opcua.figures import StepBook, machine_values
from cellctl.factory.opcua.space import (
    CLEAR_ALARM_ARGUMENTS,
    SUBMIT_ORDER_ARGUMENTS,
    CellSpace,
    machine_path,
)
from cellctl.factory.opcua.users import (
    CellRuleset,
    FileUserManager,
    load_users,
    session_user,
    track_peers,
)
from cellctl.service.access import CellAccess
from cellctl.service.methods import Caller, Dispatcher, RoleRefused
from cellctl.service.status import AlarmInfo

log = logging.getLogger(__name__)

#: cellctl's namespace: its types, enumerations and every node of the cell.
NAMESPACE = "urn:cellctl:opcua"
POLICIES = [
    ua.SecurityPolicyType.Basic256Sha256_Sign,
    ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
]
#: Shortest gap between two refreshes (a burst of changes is written once).
REFRESH_GAP = 0.02
#: The values are refreshed at least this often, told of a change or not.
REFRESH_TICK = 1.0
#: Severity of an alarm's events (OPC UA: 1 to 1000).
RAISED_SEVERITY = 700


def parse_endpoint(url: str, allow_remote: bool) -> tuple[str, int]:
    """``opc.tcp://HOST:PORT`` → (host, port); a non-loopback host only with ``allow_remote``."""
    from cellctl.service.server import parse_listen

    match = re.fullmatch(r"opc\.tcp://(\[[^\]]+\]|[^/:\[\]]+):(\d+)/?", url)
    if match is None:
        raise UsageError(f'[opcua] listen = "{url}": write "opc.tcp://HOST:PORT"')
    try:
        return parse_listen(f"{match[1]}:{match[2]}", allow_remote)
    except UsageError as e:
        raise UsageError(str(e).replace("[api]", "[opcua]").replace("the API", "OPC UA")) from None


class OpcuaServer:
    """One cell's OPC UA server (see module docstring)."""

    def __init__(
        self,
        access: CellAccess,
        table: OpcuaTable,
        *,
        name: str | None = None,
        log: Callable[[str], None] | None = None,
    ) -> None:
        if table.listen is None:
            raise UsageError("[opcua] listen is not set: no OPC UA server to start")
        self.access = access
        self.directory = Path(access.directory)
        self.dispatcher = Dispatcher(access)
        self.host, self.port = parse_endpoint(table.listen, table.allow_remote)
        self.users = self.directory / table.users if table.users else None
        self.anonymous_read = table.anonymous_read
        self.name = name or self.directory.resolve().name
        self.endpoint = f"opc.tcp://{_url_host(self.host)}:{self.port}"
        self.app_uri = f"urn:cellctl:{socket.gethostname()}:{quote(self.name, safe='')}"
        self._log = log or (lambda text: None)
        self.certificate: Path | None = None
        self._server: Server | None = None
        self._space: CellSpace | None = None
        self._steps = StepBook()
        self._alarms: dict[int, AlarmInfo] = {}
        self._conditions: AlarmConditions | None = None
        self._events: dict[str, EventGenerator] = {}
        self._changed = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    # -- life -------------------------------------------------------------------------------

    async def start(self) -> None:
        """Make the certificate if needed, build the address space, listen."""
        if self.users is not None:
            load_users(self.users)  # a missing or unsafe file is said now, not at a login
        cert, key = ensure_certificate(self.directory, self.app_uri, self.host)
        self.certificate = cert
        manager = FileUserManager(
            self.users,
            anonymous_read=self.anonymous_read,
            refused=lambda name, peer: self._log(
                f"OPC UA: login refused for user {name[:64]!r}" + (f" from {peer}" if peer else "")
            ),
        )
        asyncua_log = logging.getLogger("asyncua")
        if asyncua_log.level == logging.NOTSET:
            # Its warnings (every refused request, every client certificate without this
            # host's name) are not the cell's events; refused logins are told above.
            asyncua_log.setLevel(logging.CRITICAL)
        server = Server(user_manager=manager)  # type: ignore[arg-type]
        track_peers(server)
        bind_condition_methods(server)
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name(f"cellctl {self.name}")
        await server.set_application_uri(self.app_uri)
        server.product_uri = "urn:cellctl"
        server.manufacturer_name = "cellctl"
        server.set_security_policy(POLICIES, permission_ruleset=CellRuleset())
        tokens: list[type] = [ua.UserNameIdentityToken]
        if self.anonymous_read:
            tokens.append(ua.AnonymousIdentityToken)
        server.set_identity_tokens(tokens)
        await server.load_certificate(str(cert))
        await server.load_private_key(str(key))
        idx = await server.register_namespace(NAMESPACE)
        space = CellSpace(server, idx)
        status = self.access.status()
        machines = {
            name: status.machines[name].kind if name in status.machines else ""
            for name in self.access.machines()
        }
        await space.build(self.name, machines, self.submit_order, self.clear_alarm, self.ack_alarm)
        assert space.alarm_event_type is not None
        assert space.cell_messages is not None
        sources = {**space.messages, "": space.cell_messages}
        for source, node in sources.items():
            generator = await server.get_event_generator(space.alarm_event_type, node.nodeid)
            generator.event.SourceName = source or self.name
            self._events[source] = generator
        self._server, self._space = server, space
        self._conditions = AlarmConditions(server, space, self.dispatcher, self._log, self.name)
        await self._conditions.start()
        journal = self.access.journal()
        if journal is not None:
            self._steps.add(dataclasses.asdict(s) for s in journal.steps())
        self._alarms = {a.id: a for a in status.alarms}  # told as they come only
        await self._refresh()
        try:
            await server.start()
        except OSError as e:
            raise UsageError(f"[opcua] listen: cannot listen on {self.endpoint}: {e}") from None
        with contextlib.suppress(UsageError):
            self.access.controller().listeners.append(self.changed)
        self._task = asyncio.create_task(self._updater())

    def describe(self) -> str:
        """The line ``cellctl run`` prints: where, how secured, which certificate."""
        who = "users" + (" and anonymous readers" if self.anonymous_read else "")
        thumb = thumbprint(self.certificate) if self.certificate else "?"
        return (
            f"OPC UA on {self.endpoint} (Basic256Sha256 Sign, SignAndEncrypt; {who}; "
            f"certificate SHA-1 {thumb})"
        )

    async def close(self) -> None:
        """Stop serving (sessions are closed)."""
        with contextlib.suppress(UsageError):
            listeners = self.access.controller().listeners
            if self.changed in listeners:
                listeners.remove(self.changed)
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
        if self._server is not None:
            with contextlib.suppress(Exception):
                async with asyncio.timeout(5):
                    await self._server.stop()
            self._server = None

    # -- keeping the values current ---------------------------------------------------------

    def changed(self) -> None:
        """The cell's state changed (called by the controller)."""
        self._changed.set()

    async def _updater(self) -> None:
        while True:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(REFRESH_TICK):
                    await self._changed.wait()
            self._changed.clear()
            try:
                await self._refresh()
            except Exception:
                log.exception("OPC UA: refreshing the values failed")
            await current_clock().sleep(REFRESH_GAP)

    async def _refresh(self) -> None:
        space = self._space
        assert space is not None
        status = self.access.status()
        self._steps.add(await self.dispatcher.call("steps.list", {"since": self._steps.since()}))
        scrapped = await self.dispatcher.call("parts.list", {"statuses": ["scrapped"]})
        done = await self.dispatcher.call("parts.list", {"statuses": ["done"]})
        held = [p.id for p in status.held()]
        held_at = self._steps.machine_of_parts(held)
        scrapped_at = self._steps.machine_of_parts(p["id"] for p in scrapped)
        # OPC 40501 PartCounts counts parts, not steps: the parts done (the journal's word,
        # as the shift report's good parts) each machine worked on.
        good = self._steps.parts_through(p["id"] for p in done)
        for name in space.messages:
            view = status.machines.get(name)
            if view is None:
                continue
            counts = (good[name], held_at[name], scrapped_at[name])
            last = self._steps.last_of_machine(name)
            values = machine_values(name, view, status.alarms, last, counts)
            await space.write(machine_path(name), values)
        await space.write_path("Cell/Paused", status.cell.paused)
        await space.show_orders(status.orders)
        await space.show_alarms(status.alarms)
        await self._alarm_events(status.alarms)
        if self._conditions is not None:
            await self._conditions.update(status.alarms)

    async def _alarm_events(self, alarms: list[AlarmInfo]) -> None:
        """An event per alarm raised, acknowledged and cleared, from its machine's Messages."""
        now = {a.id: a for a in alarms}
        for alarm_id, alarm in now.items():
            before = self._alarms.get(alarm_id)
            if before is None:
                await self._emit(alarm, True)
            elif before.acked is None and alarm.acked is not None:
                await self._emit(alarm, True, "acknowledged: ")
        for alarm_id, alarm in self._alarms.items():
            if alarm_id not in now:
                await self._emit(alarm, False)
        self._alarms = now

    async def _emit(self, alarm: AlarmInfo, active: bool, word: str = "") -> None:
        machine = alarm.machine
        generator = self._events.get(machine) or self._events[""]
        event = generator.event
        event.AlarmId = ua.Variant(alarm.id, ua.VariantType.UInt32)
        event.Machine = machine
        event.Code = alarm.code
        event.Active = active
        event.Priority = alarm.priority
        event.Acked = alarm.acked is not None or not active
        event.Severity = (
            SEVERITY.get(alarm.priority, RAISED_SEVERITY) if active else CLEARED_SEVERITY
        )
        word = word if active else "cleared: "
        await generator.trigger(message=f"{word}alarm {alarm.id} {machine}: {alarm.text}")
        # The same event from the cell and the Server object, for clients that watch those.
        assert self._server is not None and self._space is not None and self._space.cell
        own = event.emitting_node
        service = self._server.iserver.subscription_service
        for node in (self._space.cell.nodeid, ua.NodeId(ua.Int32(ObjectIds.Server))):
            event.emitting_node = node
            await service.trigger_event(event)
        event.emitting_node = own

    # -- methods ----------------------------------------------------------------------------

    async def submit_order(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        """The method SubmitOrder(PartType, Quantity, Priority) → OrderId (``orders.submit``)."""
        refused = self._check(parent, args, SUBMIT_ORDER_ARGUMENTS, required=2)
        if refused is not None:
            return refused
        names = ("part_type", "qty", "priority")
        params = {name: a.Value for name, a in zip(names, args, strict=False)}
        try:
            result = await self.dispatcher.call("orders.submit", params, caller=_caller())
        except Exception as e:
            return _error(e, len(args))
        self._log(f"OPC UA: {result['message']}")
        return [ua.Variant(str(result["order"]["id"]), ua.VariantType.String)]

    async def ack_alarm(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        """The method AcknowledgeAlarm(AlarmId) → Message (``alarms.ack``)."""
        return await self._alarm_call("alarms.ack", parent, args)

    async def clear_alarm(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        """The method ClearAlarm(AlarmId) → Message (``alarms.clear``)."""
        return await self._alarm_call("alarms.clear", parent, args)

    async def _alarm_call(
        self, method: str, parent: ua.NodeId, args: tuple[ua.Variant, ...]
    ) -> Any:
        refused = self._check(parent, args, CLEAR_ALARM_ARGUMENTS, required=1)
        if refused is not None:
            return refused
        try:
            params = {"id": args[0].Value}
            result = await self.dispatcher.call(method, params, caller=_caller())
        except Exception as e:
            return _error(e, len(args))
        self._log(f"OPC UA: {result['message']}")
        return [ua.Variant(str(result["message"]), ua.VariantType.String)]

    def _check(
        self,
        parent: ua.NodeId,
        args: tuple[ua.Variant, ...],
        declared: list[tuple[str, ua.VariantType, str]],
        required: int,
    ) -> ua.CallMethodResult | None:
        """A refusal unless the call is on the Cell object with the declared arguments: as
        many as declared (the last ones may be left out down to ``required``), each a scalar
        of its declared type."""
        cell = self._space.cell if self._space is not None else None
        if cell is not None and parent != cell.nodeid:
            return _refused(
                StatusCodes.BadMethodInvalid, "the method belongs to the Cell object", len(args)
            )
        names = ", ".join(name for name, _, _ in declared)
        if len(args) > len(declared):
            return _refused(
                StatusCodes.BadTooManyArguments,
                f"{len(args)} arguments given; the method takes {names}",
                len(args),
            )
        if len(args) < required:
            return _refused(StatusCodes.BadArgumentsMissing, f"give {names}", len(args))
        results = []
        words = []
        for (name, vtype, _), arg in zip(declared, args, strict=False):
            if not isinstance(arg, ua.Variant) or arg.VariantType != vtype or arg.is_array:
                given = arg.VariantType.name if isinstance(arg, ua.Variant) else type(arg).__name__
                kind = f"an array of {given}" if getattr(arg, "is_array", False) else given
                results.append(ua.StatusCode(ua.UInt32(StatusCodes.BadTypeMismatch)))
                words.append(f"{name} must be {vtype.name}, not {kind}")
            else:
                results.append(ua.StatusCode())
        if not words:
            return None
        result = _refused(StatusCodes.BadInvalidArgument, "; ".join(words), len(args))
        result.InputArgumentResults = results  # BadTypeMismatch where the type is wrong
        return result

    @property
    def space(self) -> CellSpace | None:
        return self._space

    def node(self, path: str) -> Node:
        """The server-side node at ``path`` (tests, tools)."""
        assert self._server is not None and self._space is not None
        return self._server.get_node(self._space.node_id(path))


def _caller() -> Caller:
    """The OPC UA user calling the method being served, with their role."""
    who, role = session_user()
    return Caller(who, role)


def _error(error: BaseException, arguments: int) -> ua.CallMethodResult:
    """A refusal in the service's words: a Bad status, the words in each argument's
    diagnostic (``AdditionalInfo``)."""
    if isinstance(error, RoleRefused):
        code = StatusCodes.BadUserAccessDenied
    elif isinstance(error, UsageError):
        code = StatusCodes.BadInvalidArgument
    elif isinstance(error, (DeviceError, CellctlError)):
        code = StatusCodes.BadInvalidState
    else:
        log.exception("OPC UA: a method failed", exc_info=error)
        code = StatusCodes.BadInternalError
    return _refused(code, str(error), arguments)


def _refused(code: int, words: str, arguments: int = 1) -> ua.CallMethodResult:
    result = ua.CallMethodResult()
    result.StatusCode = ua.StatusCode(ua.UInt32(code))
    result.InputArgumentDiagnosticInfos = [
        ua.DiagnosticInfo(AdditionalInfo=ua.String(words)) for _ in range(max(arguments, 1))
    ]
    return result


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host
