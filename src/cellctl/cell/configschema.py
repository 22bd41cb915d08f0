"""The schema of ``cell.toml``: one pydantic table per TOML table, and its printed reference.

:mod:`cellctl.cell.config` checks each table of the file against these (:class:`CellFile` is the
whole file) and builds the typed :class:`~cellctl.cell.config.CellConfig` from them;
:func:`reference_table` renders the reference in docs/cell.md. Import them from
:mod:`cellctl.cell.config`, which re-exports them.
"""

from __future__ import annotations

import ipaddress
import re
from types import UnionType
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from cellctl.errors import CellctlError, UsageError
from cellctl.kinds import registry
from cellctl.link import LineSettings

Seconds = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Text = Annotated[str, Field(min_length=1)]

#: What a cell can name and hold. The factory's wire (``cellctl.mailbox.wire``) carries a cell's
#: state within these, so a cell beyond them is refused by ``check_cell``, not dropped by the
#: factory later.
MAX_NAME = 128
MAX_MACHINES = 64
MAX_PART_TYPES = 256


class _Table(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid", frozen=True, defer_build=True)


class CellTable(_Table):
    """``[cell]``: what the cell is and how the controller paces itself."""

    name: Text | None = Field(
        default=None, description="the cell's name (default: the directory's)"
    )
    robot: Text | None = Field(
        default=None, description="the machine that tends the mills (default: the first robot)"
    )
    mills: list[Text] | None = Field(
        default=None, description="the mills, in route order (default: every mill)"
    )
    poll_period: Seconds = Field(
        default=0.5, description="s: a fault is noticed within one poll period"
    )
    retries: Annotated[int, Field(ge=0, le=100)] = Field(
        default=2, description="a rejected robot start is reset and retried this many times"
    )
    fail_limit: Annotated[int, Field(ge=1, le=1000)] = Field(
        default=3, description="failures in a row before a machine is taken out of service"
    )
    done_output: Annotated[int, Field(ge=1, le=16)] = Field(
        default=6, description="the robot output the transfer programs raise when done"
    )
    transfer_timeout: Seconds = Field(default=120.0, description="s a transfer may take")
    interlock_timeout: Seconds = Field(
        default=30.0, description="s for a door or vise to reach its position"
    )
    pallet_timeout: Seconds = Field(
        default=60.0,
        description="s for the conveyor to bring a pallet once asked (then alarm, ask again)",
    )
    read_limit: Seconds | None = Field(
        default=None,
        description="s an idle robot's or the PLC's status read may take before it counts "
        "as not answering (default: half the poll period)",
    )
    time_scale: Annotated[float, Field(gt=0, le=100_000, allow_inf_nan=False)] = Field(
        default=1.0,
        description="the machines run this many times faster than a real cell's (an emulated "
        "cell writes it); the shift report's ideal times are divided by it",
    )
    door_start_timeout: Seconds | None = Field(
        default=None,
        description="s a commanded door may take to leave its end position before it counts "
        "as stuck (default: half the poll period)",
    )


class MachineTable(_Table):
    """``[machines.NAME]``: one robot or mill and how to reach it."""

    kind: Text = Field(description="the machine's kind (`cellctl kinds` lists them)")
    link: Text = Field(
        description="a serial device, rfc2217://HOST:PORT, socket://HOST:PORT or loop://"
    )
    line: Text | None = Field(
        default=None, description='line settings, e.g. "4800,7E2" (default: the kind\'s)'
    )
    setup: Text | None = Field(
        default=None,
        description="a mill's setup program (required for a mill), relative to the cell",
    )
    go_output: Text | None = Field(
        default=None, description="the PLC coil wired to the mill's GO input"
    )
    options: dict[str, Any] = Field(
        default_factory=dict,
        description="the kind's driver options (see docs/kinds.md: each kind's own table)",
    )

    @field_validator("kind")
    @classmethod
    def _kind(cls, value: str) -> str:
        try:
            registry.kind(value)  # that kind alone: the others' packages stay unread
        except UsageError:
            known = ", ".join(f"'{n}'" for n in registry.names())
            raise ValueError(f"{value!r} is not one of {known} (the installed kinds)") from None
        return value

    @field_validator("options")
    @classmethod
    def _renamed(cls, value: dict[str, Any]) -> dict[str, Any]:
        if "start_signal" in value:
            raise ValueError(
                f"start_signal is now go_output: write go_output = {value['start_signal']!r} "
                "in the machine's table, not in its options"
            )
        return value

    @field_validator("line")
    @classmethod
    def _line(cls, value: str | None) -> str | None:
        if value is not None:
            try:
                LineSettings.parse(value)
            except CellctlError as e:
                raise ValueError(str(e)) from None
        return value


class RouteStepTable(_Table):
    """One entry of ``[parts.NAME] route``: which mill runs which program."""

    mill: Text = Field(description="a mill of [cell] mills")
    program: Text = Field(description="the DYNALAN program, relative to the cell (must exist)")


class PartTable(_Table):
    """``[parts.NAME]``: a product and its route through the mills."""

    route: Annotated[list[RouteStepTable], Field(min_length=1)] = Field(
        description="a list of { mill, program }, in order"
    )


class ApiTable(_Table):
    """``[api]``: where the control API listens besides the cell's Unix socket."""

    listen: Text | None = Field(
        default=None,
        description='"HOST:PORT", e.g. "127.0.0.1:7125" (default: the Unix socket only)',
    )
    allow_remote: bool = Field(
        default=False, description="a listen address that is not loopback is refused unless true"
    )
    hosts: Annotated[
        list[Annotated[str, Field(min_length=1, max_length=253)]], Field(max_length=32)
    ] = Field(
        default_factory=list,
        description="host names the API answers to besides its address and localhost "
        "(any other Host header gets 421)",
    )
    header_timeout: Annotated[float, Field(gt=0, le=300, allow_inf_nan=False)] = Field(
        default=10.0,
        description="s a request's head may take, and its body after it, before the "
        "connection is closed",
    )
    idle_timeout: Annotated[float, Field(ge=1, le=3600, allow_inf_nan=False)] = Field(
        default=60.0, description="s an HTTP connection may sit idle between requests"
    )
    max_connections: Annotated[int, Field(ge=1, le=10_000)] = Field(
        default=100,
        description="open connections per listener; the next one closes the one idle longest "
        "(503 only when every one is busy)",
    )
    calls_per_session: Annotated[int, Field(ge=1, le=1000)] = Field(
        default=16,
        description="calls one WebSocket connection may have in flight (a batch is one); "
        "more are refused (-32010)",
    )
    calls_per_token: Annotated[int, Field(ge=1, le=10_000)] = Field(
        default=32,
        description="calls one token may have in flight over all its connections; more are "
        "refused (-32010)",
    )
    sessions_per_token: Annotated[int, Field(ge=1, le=10_000)] = Field(
        default=8,
        description="WebSocket connections one token may hold open at once; the next "
        "handshake gets 429 (less than max_connections, so a token cannot take them all)",
    )

    @model_validator(mode="after")
    def _listen(self) -> ApiTable:
        if self.listen is not None:
            loopback = _is_loopback(self.listen)
            if not loopback and not self.allow_remote:
                raise ValueError(
                    f"listen = {self.listen!r} is not a loopback address: set "
                    "allow_remote = true to answer there"
                )
        if self.calls_per_token < self.calls_per_session:
            raise ValueError(
                f"calls_per_token = {self.calls_per_token} is less than calls_per_session = "
                f"{self.calls_per_session}: one connection could never reach its own cap"
            )
        given = "sessions_per_token" in self.model_fields_set
        if given and self.sessions_per_token >= self.max_connections:
            raise ValueError(
                f"sessions_per_token = {self.sessions_per_token} is not less than "
                f"max_connections = {self.max_connections}: one token could take every "
                "connection, and nobody else could reach the cell (its emergency stop included)"
            )
        return self


class MailboxTable(_Table):
    """``[mailbox]``: orders from an MQTT broker instead of the local one (docs/factory.md)."""

    url: Text | None = Field(
        default=None,
        description='"mqtt://HOST:PORT/PREFIX" or "mqtts://..." (default: the SQLite mailbox)',
    )
    credentials: Text | None = Field(
        default=None, description="file with username and password (TOML, mode 0600)"
    )
    ca: Text | None = Field(default=None, description="CA certificate file for mqtts://")
    plan_period: Seconds | None = Field(
        default=None,
        description="s between plans of the cell's own open work, its finish published to "
        "the factory (plan_finish_s; also when its orders change); default: no plans",
    )
    plan_horizon: Annotated[float, Field(gt=0, le=31 * 86400, allow_inf_nan=False)] = Field(
        default=28800.0,
        description="s such a plan plays ahead at most (work beyond it counts as ending there)",
    )

    @model_validator(mode="after")
    def _url(self) -> MailboxTable:
        if self.url is not None:
            if not re.fullmatch(r"mqtts?://[^/:]+(:\d+)?/[\w.\-/]+", self.url):
                raise ValueError(f"url = {self.url!r}: expected mqtt://HOST:PORT/PREFIX")
            if self.credentials is None:
                raise ValueError("an MQTT mailbox needs credentials = FILE")
        return self


class OpcuaTable(_Table):
    """``[opcua]``: the cell's OPC UA server (docs/opcua.md)."""

    listen: Text | None = Field(
        default=None,
        description='"opc.tcp://HOST:PORT", e.g. "opc.tcp://127.0.0.1:4840" (default: no server)',
    )
    users: Text | None = Field(
        default=None,
        description="file of users and salted password hashes (`cellctl opcua adduser NAME`)",
    )
    anonymous_read: bool = Field(
        default=False, description="sessions without a user may read (never call or write)"
    )
    allow_remote: bool = Field(
        default=False, description="a listen address that is not loopback is refused unless true"
    )

    @model_validator(mode="after")
    def _listen(self) -> OpcuaTable:
        if self.listen is not None:
            match = re.fullmatch(r"opc\.tcp://(\[[^\]]+\]|[^/:\[\]]+):(\d+)/?", self.listen)
            if match is None:
                raise ValueError(
                    f'listen = {self.listen!r}: write "opc.tcp://HOST:PORT", '
                    'e.g. "opc.tcp://127.0.0.1:4840"'
                )
            if not _is_loopback(f"{match[1]}:{match[2]}") and not self.allow_remote:
                raise ValueError(
                    f"listen = {self.listen!r} is not a loopback address: set "
                    "allow_remote = true to answer there"
                )
            if self.users is None and not self.anonymous_read:
                raise ValueError("nobody could log in: name a users file, or anonymous_read")
        return self


def _is_loopback(text: str) -> bool:
    """Whether ``HOST:PORT`` names a loopback host; ValueError when it is not HOST:PORT."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdecimal() or not 0 < int(port) < 65536:
        raise ValueError(f'listen = {text!r}: write "HOST:PORT", e.g. "127.0.0.1:7125"')
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    return loopback


class CellFile(BaseModel):
    """The whole of ``cell.toml``. :func:`check_cell` checks each table (and each machine, part
    and robot program) on its own, so one wrong value never hides the others' problems."""

    model_config = ConfigDict(strict=True, extra="forbid", defer_build=True)

    cell: CellTable = Field(default_factory=lambda: CellTable(), description="the cell")
    machines: dict[str, MachineTable] = Field(
        default_factory=dict, description="[machines.NAME]: the robot and the mills"
    )
    plc: dict[str, Any] = Field(
        description="the cell's Modbus/TCP PLC: url, unit, timeout, poll, coils, inputs "
        "(see cellctl.protocol.plc)"
    )
    robot_programs: dict[str, Text] = Field(
        default_factory=dict, description="AML/E source of each transfer, SOURCE_to_TARGET = path"
    )
    parts: dict[str, PartTable] = Field(
        default_factory=dict, description="[parts.NAME]: the products and their routes"
    )
    api: ApiTable = Field(default_factory=lambda: ApiTable(), description="the control API")
    mailbox: MailboxTable = Field(
        default_factory=lambda: MailboxTable(), description="where orders come from"
    )
    opcua: OpcuaTable = Field(default_factory=lambda: OpcuaTable(), description="the OPC UA server")


#: The tables of :class:`CellFile` whose entries each have their own schema.
_PER_ENTRY: dict[str, type[_Table]] = {"machines": MachineTable, "parts": PartTable}
_TABLES: dict[str, type[_Table]] = {
    "cell": CellTable,
    "api": ApiTable,
    "mailbox": MailboxTable,
    "opcua": OpcuaTable,
}


def reference_table() -> str:
    """The reference of ``cell.toml`` in docs/cell.md, rendered from the schema."""
    out = ["| key | type | default | meaning |", "|---|---|---|---|"]
    sections: list[tuple[str, type[BaseModel]]] = [
        ("[cell]", CellTable),
        ("[machines.NAME]", MachineTable),
        ("[parts.NAME] route[n]", RouteStepTable),
        ("[api]", ApiTable),
        ("[mailbox]", MailboxTable),
        ("[opcua]", OpcuaTable),
    ]
    for title, model in sections:
        for key, info in model.model_fields.items():
            default = (
                "required"
                if info.is_required()
                else _shown(info.get_default(call_default_factory=True))
            )
            out.append(
                f"| `{title} {key}` | {_type_name(info.annotation, info.metadata)} | "
                f"{default} | {info.description or ''} |"
            )
    for key in ("plc", "robot_programs"):
        info = CellFile.model_fields[key]
        out.append(
            f"| `[{key}]` | table | {'required' if info.is_required() else '{}'} | "
            f"{info.description or ''} |"
        )
    return "\n".join(out) + "\n"


def _shown(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "{}"
    return (
        f"`{value!r}`"
        if isinstance(value, str)
        else f"{value:g}"
        if isinstance(value, float)
        else str(value)
    )


def _type_name(annotation: Any, metadata: list[Any]) -> str:
    args = [a for a in get_args(annotation) if a is not type(None)]
    origin = get_origin(annotation)
    if origin is Annotated:
        return _type_name(args[0], [*metadata, *annotation.__metadata__])
    if origin in (Union, UnionType):
        return _type_name(args[0], metadata)
    if origin is Literal:
        return "one of " + ", ".join(f"`{a}`" for a in get_args(annotation))
    if origin is list:
        return f"list of {_type_name(args[0], [])}s"
    if origin is dict:
        return "table"
    names = {float: "number", int: "integer", str: "string", bool: "boolean"}
    name = names.get(annotation, getattr(annotation, "__name__", str(annotation)))
    bounds = []
    for item in metadata:
        for attr, sign in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            if getattr(item, attr, None) is not None:
                bounds.append(f"{sign} {getattr(item, attr)}")
    return f"{name} {' and '.join(bounds)}" if bounds else name
