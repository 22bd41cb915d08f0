"""The cell's alarms as OPC UA AlarmConditionType conditions (Part 9), with Acknowledge.

Each open alarm is a condition whose ConditionId is its ``Cell/Alarms/<id>`` object; an event
of AlarmConditionType is sent when it is raised, acknowledged (on any surface), returned to
normal or cleared, from its machine's ``Notification/Messages`` (or ``Cell/Messages``) with
``Retain`` true while the alarm is open, so ConditionRefresh gives every open one again. The
standard ``Acknowledge(EventId, Comment)`` method, called on a condition, is the control API's
``alarms.ack``::

    conditions = AlarmConditions(server, space, dispatcher, log)
    await conditions.start()               # after the space is built
    await conditions.update(status.alarms)  # on every refresh
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from asyncua import ua
from asyncua.server.event_generator import EventGenerator
from asyncua.server.server import Server
from asyncua.ua.object_ids import ObjectIds
from asyncua.ua.status_codes import StatusCodes

from cellctl.errors import CellctlError
from cellctl.factory.opcua.space import CellSpace
from cellctl.factory.opcua.users import session_user
from cellctl.service.methods import Caller, Dispatcher, RoleRefused
from cellctl.service.status import AlarmInfo

#: An open alarm's severity by its priority (ISA-18.2's high, medium, low); cleared: 100.
SEVERITY = {"high": 900, "medium": 500, "low": 200}
CLEARED_SEVERITY = 100


def bind_condition_methods(server: Server) -> None:
    """Serve ConditionRefresh (call before ``server.init()``)."""
    server.iserver.bind_condition_methods = True


class AlarmConditions:
    """The open alarms' conditions of one server (see module docstring)."""

    def __init__(
        self,
        server: Server,
        space: CellSpace,
        dispatcher: Dispatcher,
        log: Callable[[str], None],
        cell_name: str,
    ) -> None:
        self.server = server
        self.space = space
        self.dispatcher = dispatcher
        self._log = log
        self._cell_name = cell_name
        self._generator: EventGenerator | None = None
        self._told: dict[int, AlarmInfo] = {}

    async def start(self) -> None:
        """The event generator, and Acknowledge bound to ``alarms.ack``."""
        assert self.space.cell is not None
        self._generator = await self.server.get_event_generator(
            ObjectIds.AlarmConditionType, self.space.cell.nodeid
        )
        self.server.iserver.isession.add_method_callback(
            ua.NodeId(ua.Int32(ObjectIds.AcknowledgeableConditionType_Acknowledge)),
            self.acknowledge,
        )

    async def update(self, alarms: list[AlarmInfo]) -> None:
        """Send a condition event for each alarm raised, acknowledged, returned to normal or
        cleared since the last update."""
        now = {a.id: a for a in alarms}
        for alarm_id, alarm in now.items():
            before = self._told.get(alarm_id)
            if (
                before is None
                or (before.acked is None) != (alarm.acked is None)
                or (before.returned is None) != (alarm.returned is None)
            ):
                await self._emit(alarm, open_=True)
        for alarm_id, alarm in self._told.items():
            if alarm_id not in now:
                await self._emit(alarm, open_=False)
        self._told = now

    async def _emit(self, alarm: AlarmInfo, *, open_: bool) -> None:
        assert self._generator is not None
        event = self._generator.event
        source = self.space.messages.get(alarm.machine) or self.space.cell_messages
        assert source is not None
        event.SourceNode = source.nodeid
        event.SourceName = alarm.machine if alarm.machine in self.space.messages else ""
        event.SourceName = event.SourceName or self._cell_name
        event.NodeId = self.space.node_id(f"Cell/Alarms/{alarm.id}")  # the ConditionId
        event.ConditionName = f"{alarm.machine} {alarm.code}"
        event.ConditionClassId = ua.NodeId(ua.Int32(ObjectIds.BaseConditionClassType))
        event.ConditionClassName = ua.LocalizedText("BaseConditionClass")
        event.Retain = open_
        event.Severity = SEVERITY.get(alarm.priority, 500) if open_ else CLEARED_SEVERITY
        active = open_ and alarm.returned is None
        acked = alarm.acked is not None or not open_
        _two_state(event, "EnabledState", True, "Enabled", "Disabled")
        _two_state(event, "ActiveState", active, "Active", "Inactive")
        _two_state(event, "AckedState", acked, "Acknowledged", "Unacknowledged")
        _two_state(event, "ConfirmedState", True, "Confirmed", "Unconfirmed")
        word = "" if open_ else "cleared: "
        await self._generator.trigger(
            message=f"{word}alarm {alarm.id} {alarm.machine}: {alarm.text}"
        )
        # The same event from the Server object, where a generic A&C client subscribes.
        own = event.emitting_node
        event.emitting_node = ua.NodeId(ua.Int32(ObjectIds.Server))
        await self.server.iserver.subscription_service.trigger_event(event)
        event.emitting_node = own

    async def acknowledge(self, parent: ua.NodeId, *args: Any) -> Any:
        """Acknowledge(EventId: ByteString, Comment: LocalizedText) on a condition: the
        control API's ``alarms.ack`` for the alarm whose ``Cell/Alarms/<id>`` it is."""
        alarm_id = self.space.alarm_of(parent)
        if alarm_id is None:  # not an open alarm's condition
            return ua.StatusCode(ua.UInt32(StatusCodes.BadNodeIdUnknown))
        told = self._told.get(alarm_id)
        if told is not None and told.acked is not None:
            return ua.StatusCode(ua.UInt32(StatusCodes.BadConditionBranchAlreadyAcked))
        try:
            caller = Caller(*session_user())
            result = await self.dispatcher.call("alarms.ack", {"id": alarm_id}, caller=caller)
        except RoleRefused:  # a viewer (refused in the audit trail)
            return ua.StatusCode(ua.UInt32(StatusCodes.BadUserAccessDenied))
        except CellctlError:  # cleared meanwhile
            return ua.StatusCode(ua.UInt32(StatusCodes.BadInvalidState))
        self._log(f"OPC UA: {result['message']}")
        return []


def _two_state(event: Any, name: str, value: bool, true: str, false: str) -> None:
    setattr(event, name, ua.LocalizedText(true if value else false))
    setattr(event, f"{name}/Id", value)
