"""The cell's OPC UA address space: the node tree, built once, and the writes that keep its
values current (docs/opcua.md draws the tree).

::

    space = CellSpace(server, namespace_index)
    await space.build("lab cell", {"robot": robot_kind, "cnc1": mill_kind}, submit, clear)
    await space.write("Machines/cnc1", machine_values(...))   # only changed values are written
    await space.show_orders(status.orders); await space.show_alarms(status.alarms)

Every node id is a string in cellctl's namespace, the browse path joined with ``/``
(``Machines/cnc1/Monitoring/MachineState``, ``Cell/Orders/A/State``), so a client may keep
it.
"""

from __future__ import annotations

import datetime
from collections.abc import Awaitable, Callable
from typing import Any
from urllib.parse import quote

from asyncua import ua
from asyncua.common.node import Node
from asyncua.common.structures104 import new_enum
from asyncua.server.server import Server
from asyncua.ua.object_ids import ObjectIds

from cellctl.factory.opcua.figures import (
    CHANNEL_STATES,
    IDENTIFICATION,
    MACHINE_CONDITIONS,
    OPERATION_MODES,
    PROGRAM_STATES,
    SIGNAL_COLORS,
)
from cellctl.service.status import AlarmInfo, OrderInfo

V = ua.VariantType
#: The per-machine variables: path, type, enumeration (None: a plain value), initial value.
MACHINE_VARIABLES: list[tuple[str, ua.VariantType, str | None, Any]] = [
    ("Identification/Manufacturer", V.String, None, ""),
    ("Identification/Model", V.String, None, ""),
    ("Identification/Name", V.String, None, ""),
    ("Monitoring/MachineState", V.String, None, ""),
    ("Monitoring/Condition", V.Int32, "MachineCondition", 0),
    ("Monitoring/OperationMode", V.Int32, "MachineOperationMode", 1),
    ("Monitoring/StacklightColour", V.Int32, "SignalColor", 0),
    ("Monitoring/InService", V.Boolean, None, True),
    ("Monitoring/OutOfServiceReason", V.String, None, ""),
    ("Monitoring/Channel/ChannelState", V.Int32, "ChannelState", 2),
    ("Monitoring/Channel/ProgramState", V.Int32, "ProgramState", 2),
    ("Monitoring/Channel/CurrentStep", V.String, None, ""),
    ("Production/ActiveProgram/Name", V.String, None, ""),
    ("Production/ActiveProgram/PartId", V.String, None, ""),
    ("Production/ActiveProgram/State", V.Int32, "ProgramState", 2),
    ("Production/ActiveProgram/Progress", V.Double, None, 0.0),
    ("Production/PartCounts/Good", V.UInt32, None, 0),
    ("Production/PartCounts/Held", V.UInt32, None, 0),
    ("Production/PartCounts/Scrapped", V.UInt32, None, 0),
    ("Notification/ActiveAlarms", V.UInt32, None, 0),
]
CELL_VARIABLES: list[tuple[str, ua.VariantType, Any]] = [
    ("Name", V.String, ""),
    ("Paused", V.Boolean, False),
    ("OpenOrders", V.UInt32, 0),
    ("ActiveAlarms", V.UInt32, 0),
]
ORDER_VARIABLES: list[tuple[str, str, ua.VariantType]] = [
    ("PartType", "part_type", V.String),
    ("Quantity", "qty", V.UInt32),
    ("Priority", "priority", V.Int32),
    ("State", "state", V.String),
    ("Note", "note", V.String),
    ("PartsDone", "done", V.UInt32),
    ("PartsHeld", "held", V.UInt32),
    ("PartsScrapped", "scrapped", V.UInt32),
    ("Due", "due_time", V.DateTime),
    ("Late", "late", V.Boolean),
]
#: An order's Due when it has no due time: OPC UA's null DateTime (encoded as 0, 1601-01-01).
NO_DUE = datetime.datetime(1601, 1, 1, tzinfo=datetime.UTC)
ALARM_VARIABLES: list[tuple[str, str, ua.VariantType]] = [
    ("AlarmId", "id", V.UInt32),
    ("Machine", "machine", V.String),
    ("Code", "code", V.String),
    ("Text", "text", V.String),
    ("Raised", "raised", V.DateTime),
    ("Priority", "priority", V.String),
    ("Acked", "acked_flag", V.Boolean),
    ("ReturnedToNormal", "returned_flag", V.Boolean),
]
ENUMS = {
    "MachineCondition": MACHINE_CONDITIONS,
    "MachineOperationMode": OPERATION_MODES,
    "SignalColor": SIGNAL_COLORS,
    "ChannelState": CHANNEL_STATES,
    "ProgramState": PROGRAM_STATES,
}
OPEN_ORDER_STATES = ("posted", "accepted", "in-progress", "held")
#: An alarm's event: BaseEventType's fields and these.
ALARM_EVENT_FIELDS = [
    ("AlarmId", V.UInt32),
    ("Machine", V.String),
    ("Code", V.String),
    ("Active", V.Boolean),
    ("Priority", V.String),
    ("Acked", V.Boolean),
]
Method = Callable[..., Awaitable[Any]]
#: The methods' input arguments: name, type, description (the server checks calls by these).
SUBMIT_ORDER_ARGUMENTS: list[tuple[str, ua.VariantType, str]] = [
    ("PartType", V.String, "a part type of the cell"),
    ("Quantity", V.UInt32, "parts to make (1 to 10000)"),
    ("Priority", V.Int32, "higher first (default 0)"),
]
CLEAR_ALARM_ARGUMENTS: list[tuple[str, ua.VariantType, str]] = [
    ("AlarmId", V.UInt32, "the alarm's id (Cell/Alarms)"),
]


def machine_path(name: str) -> str:
    """Where machine ``name``'s object is: ``Machines/<name>``."""
    return f"Machines/{_key(name)}"


def _key(text: str) -> str:
    """An id as a node id part: ``/`` and ``%`` escaped so paths stay unambiguous."""
    return quote(text, safe=" -_.:,;()[]{}#@!+=~*")


class CellSpace:
    """The node tree of one cell (see module docstring)."""

    def __init__(self, server: Server, idx: int) -> None:
        self.server = server
        self.idx = idx
        self.nodes: dict[str, tuple[Node, ua.VariantType]] = {}
        self.values: dict[str, Any] = {}
        self.messages: dict[str, Node] = {}  # machine name -> its Notification/Messages
        self.cell: Node | None = None
        self.cell_messages: Node | None = None
        self.alarm_event_type: Node | None = None
        self._orders: dict[str, Node] = {}
        self._alarms: dict[int, Node] = {}
        self._enums: dict[str, ua.NodeId] = {}

    def node_id(self, path: str) -> ua.NodeId:
        return ua.NodeId(ua.String(path), ua.Int16(self.idx))

    async def build(
        self,
        cell_name: str,
        machines: dict[str, str],
        submit: Method,
        clear: Method,
        ack: Method | None = None,
    ) -> None:
        """The tree: ``Machines/<name>/...`` per machine, ``Cell`` with its orders, alarms
        and the two methods."""
        server, idx = self.server, self.idx
        for name, fields in ENUMS.items():
            self._enums[name] = (await new_enum(server, idx, name, list(fields))).nodeid
        self.alarm_event_type = await server.create_custom_event_type(
            idx, "CellAlarmEventType", ObjectIds.BaseEventType, ALARM_EVENT_FIELDS
        )
        objects = server.nodes.objects
        folder = await objects.add_folder(
            self.node_id("Machines"), ua.QualifiedName("Machines", idx)
        )
        for name, kind in machines.items():
            machine = await folder.add_object(
                self.node_id(f"Machines/{_key(name)}"), ua.QualifiedName(name, idx)
            )
            await self._machine(machine, name, kind)
        cell = await objects.add_object(self.node_id("Cell"), ua.QualifiedName("Cell", idx))
        self.cell = cell
        for var, vtype, value in CELL_VARIABLES:
            await self._variable(cell, f"Cell/{var}", vtype, value)
        await self.write_path("Cell/Name", cell_name)
        await cell.add_folder(self.node_id("Cell/Orders"), ua.QualifiedName("Orders", idx))
        await cell.add_folder(self.node_id("Cell/Alarms"), ua.QualifiedName("Alarms", idx))
        self.cell_messages = await cell.add_object(
            self.node_id("Cell/Messages"), ua.QualifiedName("Messages", idx)
        )
        await cell.add_method(
            self.node_id("Cell/SubmitOrder"),
            ua.QualifiedName("SubmitOrder", idx),
            submit,
            [_argument(*a) for a in SUBMIT_ORDER_ARGUMENTS],
            [_argument("OrderId", V.String, "the order's id")],
        )
        await cell.add_method(
            self.node_id("Cell/ClearAlarm"),
            ua.QualifiedName("ClearAlarm", idx),
            clear,
            [_argument(*a) for a in CLEAR_ALARM_ARGUMENTS],
            [_argument("Message", V.String, "what was done")],
        )
        if ack is not None:
            await cell.add_method(
                self.node_id("Cell/AcknowledgeAlarm"),
                ua.QualifiedName("AcknowledgeAlarm", idx),
                ack,
                [_argument(*a) for a in CLEAR_ALARM_ARGUMENTS],
                [_argument("Message", V.String, "what was done")],
            )
        # Events: each Messages object, the cell and the Server object (where a generic
        # client looks) all notify; the notifier references let a client find them.
        await cell.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        await server.nodes.server.add_reference(cell.nodeid, ObjectIds.HasNotifier)
        for node in [*self.messages.values(), self.cell_messages]:
            await cell.add_reference(node.nodeid, ObjectIds.HasNotifier)

    async def _machine(self, machine: Node, name: str, kind: str) -> None:
        base = f"Machines/{_key(name)}"
        parents: dict[str, Node] = {"": machine}
        for path, vtype, enum, value in MACHINE_VARIABLES:
            folder, _, _ = path.rpartition("/")
            parent = await self._parents(parents, base, folder)
            await self._variable(parent, f"{base}/{path}", vtype, value, enum)
        notification = await self._parents(parents, base, "Notification")
        self.messages[name] = await notification.add_object(
            self.node_id(f"{base}/Notification/Messages"), ua.QualifiedName("Messages", self.idx)
        )
        manufacturer, model = IDENTIFICATION.get(kind, ("", kind))
        await self.write(
            base,
            {
                "Identification/Manufacturer": manufacturer,
                "Identification/Model": model,
                "Identification/Name": name,
            },
        )

    async def _parents(self, parents: dict[str, Node], base: str, folder: str) -> Node:
        """The object at ``folder`` under ``base``, made (with its parents) if needed."""
        if folder not in parents:
            above, _, last = folder.rpartition("/")
            parent = await self._parents(parents, base, above)
            parents[folder] = await parent.add_object(
                self.node_id(f"{base}/{folder}"), ua.QualifiedName(last, self.idx)
            )
        return parents[folder]

    async def _variable(
        self,
        parent: Node,
        path: str,
        vtype: ua.VariantType,
        value: Any,
        enum: str | None = None,
    ) -> Node:
        datatype = self._enums[enum] if enum else None
        node = await parent.add_variable(
            self.node_id(path),
            ua.QualifiedName(path.rpartition("/")[2], self.idx),
            ua.Variant(value, vtype),
            datatype=datatype,
        )
        self.nodes[path] = (node, vtype)
        self.values[path] = value
        return node

    # -- values -------------------------------------------------------------------------------

    async def write(self, prefix: str, values: dict[str, Any]) -> None:
        """Write ``prefix/path`` for each of ``values`` that changed."""
        for path, value in values.items():
            await self.write_path(f"{prefix}/{path}", value)

    async def write_path(self, path: str, value: Any) -> None:
        if self.values.get(path, _UNSET) == value:
            return
        node, vtype = self.nodes[path]
        self.values[path] = value
        await self.server.write_attribute_value(node.nodeid, ua.DataValue(ua.Variant(value, vtype)))

    async def show_orders(self, orders: list[OrderInfo]) -> None:
        """``Cell/Orders/<id>``: the orders of the status (open ones and the latest)."""
        wanted = {o.id: o.model_dump() for o in orders}
        for order_id in [i for i in self._orders if i not in wanted]:
            await self._remove(f"Cell/Orders/{_key(order_id)}", self._orders.pop(order_id))
        for order_id, order in wanted.items():
            base = f"Cell/Orders/{_key(order_id)}"
            parts = order.get("parts") or {}
            row = {**order, **{k: int(parts.get(k, 0)) for k in ("done", "held", "scrapped")}}
            row["due_time"] = NO_DUE if order["due"] is None else _utc(float(order["due"]))
            if order_id not in self._orders:
                self._orders[order_id] = await self._record(
                    "Cell/Orders", base, order_id, ORDER_VARIABLES, row
                )
            for var, field, _ in ORDER_VARIABLES:
                await self.write_path(f"{base}/{var}", row[field])
        await self.write_path(
            "Cell/OpenOrders", sum(1 for o in orders if o.state in OPEN_ORDER_STATES)
        )

    async def show_alarms(self, alarms: list[AlarmInfo]) -> None:
        """``Cell/Alarms/<id>``: the open alarms, with their priority, acknowledged and
        returned-to-normal flags kept current."""
        wanted = {a.id: a.model_dump() for a in alarms}
        for alarm_id in [i for i in self._alarms if i not in wanted]:
            await self._remove(f"Cell/Alarms/{alarm_id}", self._alarms.pop(alarm_id))
        for alarm_id, alarm in wanted.items():
            base = f"Cell/Alarms/{alarm_id}"
            row = {
                **alarm,
                "raised": _utc(float(alarm.get("raised", 0.0))),
                "acked_flag": alarm.get("acked") is not None,
                "returned_flag": alarm.get("returned") is not None,
            }
            if alarm_id not in self._alarms:
                self._alarms[alarm_id] = await self._record(
                    "Cell/Alarms", base, str(alarm_id), ALARM_VARIABLES, row
                )
            for var in ("Acked", "ReturnedToNormal"):
                field = next(f for v, f, _ in ALARM_VARIABLES if v == var)
                await self.write_path(f"{base}/{var}", row[field])
        await self.write_path("Cell/ActiveAlarms", len(wanted))

    def alarm_of(self, node: ua.NodeId) -> int | None:
        """The id of the open alarm whose ``Cell/Alarms/<id>`` object ``node`` is."""
        for alarm_id, found in self._alarms.items():
            if found.nodeid == node:
                return alarm_id
        return None

    async def _record(
        self,
        folder: str,
        base: str,
        name: str,
        fields: list[tuple[str, str, ua.VariantType]],
        row: dict[str, Any],
    ) -> Node:
        parent = self.server.get_node(self.node_id(folder))
        node = await parent.add_object(self.node_id(base), ua.QualifiedName(name, self.idx))
        for var, field, vtype in fields:
            await self._variable(node, f"{base}/{var}", vtype, row[field])
        return node

    async def _remove(self, base: str, node: Node) -> None:
        await self.server.delete_nodes([node], recursive=True)
        for path in [p for p in self.nodes if p.startswith(base + "/")]:
            del self.nodes[path]
            self.values.pop(path, None)


_UNSET = object()


def _argument(name: str, vtype: ua.VariantType, description: str) -> ua.Argument:
    arg = ua.Argument()
    arg.Name = name
    arg.DataType = ua.NodeId(ua.Int32(vtype.value))
    arg.ValueRank = -1
    arg.Description = ua.LocalizedText(description)
    return arg


def _utc(seconds: float) -> datetime.datetime:
    return datetime.datetime.fromtimestamp(seconds, datetime.UTC)
