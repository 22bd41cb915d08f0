"""The cell described in one file: ``cell.toml`` in the cell directory.

::

    [cell]
    name = "CIM laboratory machining cell"
    robot = "robot"                       # the machine that tends the mills
    mills = ["cnc1", "cnc2"]              # in route order: CNC 1 roughing, CNC 2 finishing
    poll_period = 0.5                     # s: a fault is noticed within one poll period

    [machines.robot]
    kind = "..."                          # a robot kind: `cellctl kinds` lists them
    link = "rfc2217://127.0.0.1:7001"
    line = "4800,7E2"

    [machines.cnc1]
    kind = "..."                          # a mill kind
    link = "rfc2217://127.0.0.1:7002"
    setup = "programs/cnc1_setup.dyn"     # paths are relative to the cell directory
    go_output = "go1"                     # the PLC coil wired to the mill's GO input

    [plc]
    url = "modbus://127.0.0.1:5020"       # coils/inputs tables optional (assumed defaults)

    [robot_programs]                      # AML/E source of each transfer
    conveyor_to_cnc1 = "robot/conveyor_to_cnc1.aml"
    cnc1_to_cnc2 = "robot/cnc1_to_cnc2.aml"
    cnc2_to_conveyor = "robot/cnc2_to_conveyor.aml"

    [parts.wax-robot-base]
    route = [
      { mill = "cnc1", program = "programs/robot_base_rough_cnc1.dyn" },
      { mill = "cnc2", program = "programs/robot_base_finish_cnc2.dyn" },
    ]

:func:`check_cell` reads and checks all of it — programs included, with the DYNALAN validator
and the AML/E compiler — and returns every problem; :func:`load_cell` returns the checked
:class:`CellConfig` or raises :class:`UsageError` listing the problems.
"""

from __future__ import annotations

import ipaddress
import itertools
import re
from dataclasses import dataclass, field
from pathlib import Path
from types import UnionType
from typing import Annotated, Any, Literal, TypeVar, Union, get_args, get_origin

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from cellctl.errors import CellctlError, UsageError
from cellctl.kinds import registry
from cellctl.kinds.kind import MachineKind, ProgramRole
from cellctl.link import LineSettings

#: Where a part can be; the conveyor is where parts come from and go back to.
CONVEYOR = "conveyor"


def robot_kinds() -> tuple[str, ...]:
    """The installed kinds of the robot family (from the registry)."""
    return registry.names("robot")


def mill_kinds() -> tuple[str, ...]:
    """The installed kinds of the mill family (from the registry)."""
    return registry.names("mill")


def transfer_name(source: str, target: str) -> str:
    """The robot program that moves a part from ``source`` to ``target``: ``cnc1_to_cnc2``."""
    return f"{source}{_TO}{target}"


def transfer_ends(program: str) -> tuple[str, str]:
    """The two places a transfer program joins: ``cnc1_to_cnc2`` → ``("cnc1", "cnc2")``."""
    source, sep, target = program.partition(_TO)
    if not sep:
        raise UsageError(f"{program!r} is not a transfer program name (SOURCE_to_TARGET)")
    return source, target


_TO = "_to_"


@dataclass(frozen=True)
class MachineConfig:
    """One machine of the cell as ``cell.toml`` describes it."""

    name: str
    kind: str
    link: str
    line: LineSettings
    options: dict[str, Any] = field(default_factory=dict)
    setup: Path | None = None
    go_output: str | None = None

    @property
    def family(self) -> str:
        """``robot`` or ``mill``: what the cell does with it."""
        return registry.family_of(self.kind)


@dataclass(frozen=True)
class RouteStep:
    """One machining operation of a part's route: which mill runs which program."""

    mill: str
    program: Path
    name: str
    lines: int
    machining_s: float


@dataclass(frozen=True)
class PartType:
    """A product the cell makes and the route it takes through the mills."""

    name: str
    route: tuple[RouteStep, ...]

    def transfers(self) -> list[str]:
        """The robot programs this part needs, in order."""
        stops = [CONVEYOR, *(s.mill for s in self.route), CONVEYOR]
        return [transfer_name(a, b) for a, b in itertools.pairwise(stops)]


@dataclass
class CellConfig:
    """The checked cell: machines, PLC, robot programs (compiled) and part types."""

    directory: Path
    name: str
    robot: MachineConfig
    mills: list[MachineConfig]
    plc: dict[str, Any]
    robot_programs: dict[str, Any]
    parts: dict[str, PartType]
    poll_period: float = 0.5
    raw: dict[str, Any] = field(default_factory=dict)
    api_listen: str | None = None  # [api] listen: "HOST:PORT"; None = the Unix socket only
    api_allow_remote: bool = False  # [api] allow_remote: a non-loopback listen is allowed
    api: ApiTable | None = None  # [api]: hosts, timeouts, connections
    mailbox: MailboxTable | None = None  # [mailbox]: url None = the SQLite mailbox
    opcua: OpcuaTable | None = None  # [opcua]: listen None = no OPC UA server

    def machine(self, name: str) -> MachineConfig:
        """The robot or mill called ``name``."""
        for m in [self.robot, *self.mills]:
            if m.name == name:
                return m
        raise UsageError(f"unknown machine {name!r}")


# --- the schema: cell.toml described once -------------------------------------------------------

Seconds = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Text = Annotated[str, Field(min_length=1)]

#: What a cell can name and hold. The factory's wire (``cellctl.mailbox.wire``) carries a cell's
#: state within these, so a cell beyond them is refused here, not dropped by the factory later.
MAX_NAME = 128
MAX_MACHINES = 64
MAX_PART_TYPES = 256


class _Table(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid", frozen=True)


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
        if value not in registry.names():
            known = ", ".join(f"'{n}'" for n in registry.names())
            raise ValueError(f"{value!r} is not one of {known} (the installed kinds)")
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
        default=10.0, description="s a request's head may take before the connection is closed"
    )
    idle_timeout: Annotated[float, Field(ge=1, le=3600, allow_inf_nan=False)] = Field(
        default=60.0, description="s an HTTP connection may sit idle between requests"
    )
    max_connections: Annotated[int, Field(ge=1, le=10_000)] = Field(
        default=100, description="open connections per listener; the next one gets 503"
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

    model_config = ConfigDict(strict=True, extra="forbid")

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


# --- reading and checking -----------------------------------------------------------------------


def _load_toml(directory: Path) -> tuple[dict[str, Any], str]:
    import tomllib

    path = directory / "cell.toml"
    try:
        text = path.read_text(encoding="utf-8")
        return tomllib.loads(text), text
    except FileNotFoundError:
        raise UsageError(
            f"{path}: no such file (create it, or run 'cellctl emulate cell')"
        ) from None
    except OSError as e:
        raise UsageError(f"{path}: cannot read: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise UsageError(f"{path}: not UTF-8 text: {e.reason}") from None
    except tomllib.TOMLDecodeError as e:
        raise UsageError(f"{path}: not valid TOML: {e}") from None


class _Problems:
    """Problems found so far, each with its TOML path and, where found, its line."""

    def __init__(self, text: str) -> None:
        self.lines = text.splitlines()
        self.items: list[str] = []

    def add(self, message: str) -> None:
        self.items.append(message)

    def at(self, loc: tuple[str | int, ...], message: str) -> None:
        self.items.append(f"{_path(loc)}: {message}{self._line(loc)}")

    def schema(self, loc: tuple[str | int, ...], error: ValidationError) -> None:
        for item in error.errors(include_url=False):
            where = loc + tuple(item["loc"])
            self.at(where, _message(item))

    def _line(self, loc: tuple[str | int, ...]) -> str:
        keys = [k for k in loc if isinstance(k, str)]
        if not keys:
            return ""
        found = None
        for depth in range(len(keys), 0, -1):
            header = _header(keys[:depth])
            start = next((i for i, t in enumerate(self.lines) if _header_of(t) == header), None)
            if start is None:
                continue
            found = start
            rest = keys[depth:]
            if rest:
                key = re.compile(rf"^\s*\"?{re.escape(rest[0])}\"?\s*=")
                for i in range(start + 1, len(self.lines)):
                    if _header_of(self.lines[i]) is not None:
                        break
                    if key.match(self.lines[i]):
                        found = i
                        break
            break
        return f" (line {found + 1})" if found is not None else ""


def _header(keys: list[str]) -> str:
    return ".".join(keys)


def _header_of(line: str) -> str | None:
    match = re.match(r"^\s*\[+\s*([^\]]+?)\s*\]+\s*(?:#.*)?$", line)
    if match is None:
        return None
    return ".".join(part.strip().strip("\"'") for part in match.group(1).split("."))


def _path(loc: tuple[str | int, ...]) -> str:
    """``("machines", "cnc1", "kind")`` → ``[machines.cnc1] kind``."""
    depth = 2 if loc and loc[0] in _PER_ENTRY else 1
    table = ".".join(str(k) for k in loc[:depth])
    rest = ""
    for key in loc[depth:]:
        rest += f"[{key + 1}]" if isinstance(key, int) else (f".{key}" if rest else key)
    return f"[{table}] {rest}".rstrip() if rest else f"[{table}]"


def _message(item: Any) -> str:
    kind = item["type"]
    if kind == "missing":
        return "missing"
    if kind == "extra_forbidden":
        return "unknown key"
    shown = repr(item.get("input"))
    shown = shown if len(shown) <= 60 else shown[:57] + "..."
    if kind == "literal_error":
        return f"{shown} is not {item['ctx']['expected']}"
    message = str(item["msg"])
    if message.startswith("Value error, "):
        message = message[len("Value error, ") :]
    return f"{message}, not {shown}"


def _checked(
    model: type[_T], data: Any, loc: tuple[str | int, ...], problems: _Problems
) -> _T | None:
    try:
        return model.model_validate(data)
    except ValidationError as e:
        problems.schema(loc, e)
        return None


_T = TypeVar("_T", bound=BaseModel)


def _entries(raw: dict[str, Any], key: str, problems: _Problems) -> dict[str, Any]:
    """A table of tables (``[machines]``, ``[parts]``...), or {} after reporting it is not one."""
    value = raw.get(key, {})
    if not isinstance(value, dict):
        problems.at((key,), f"must be a table, not {type(value).__name__}")
        return {}
    return value


def _check_sizes(
    raw: dict[str, Any], cell_raw: dict[str, Any], directory: Path, problems: _Problems
) -> None:
    """Names and counts within what the factory's wire carries (:data:`MAX_NAME`...)."""
    name = cell_raw.get("name")
    cell_name = name if isinstance(name, str) else directory.resolve().name
    if len(cell_name) > MAX_NAME:
        problems.at(("cell", "name"), f"{len(cell_name)} characters: at most {MAX_NAME}")
    for key, most in (("machines", MAX_MACHINES), ("parts", MAX_PART_TYPES)):
        table = raw.get(key)
        if not isinstance(table, dict):
            continue
        if len(table) > most:
            problems.at((key,), f"{len(table)} entries: a cell has at most {most}")
        for entry in table:
            if len(entry) > MAX_NAME:
                problems.at((key,), f"{entry[:20]}…: {len(entry)} characters: at most {MAX_NAME}")


def check_cell(directory: Path | str) -> tuple[CellConfig | None, list[str]]:
    """Read and check ``<directory>/cell.toml``; return the config (if usable) and problems.

    The file is checked against :class:`CellFile` table by table, then the cross-references
    (robot and mills, routes, program files, PLC coils); every problem is returned at once,
    each with its TOML path and, where it can be found, its line.
    """
    directory = Path(directory)
    try:
        raw, text = _load_toml(directory)
    except UsageError as e:
        return None, [str(e)]
    problems = _Problems(text)
    for key in raw:
        if key not in CellFile.model_fields:
            problems.at((key,), f"unknown table; known: {', '.join(CellFile.model_fields)}")
    cell = _checked(CellTable, raw.get("cell", {}), ("cell",), problems)
    api = _checked(ApiTable, raw.get("api", {}), ("api",), problems)
    mailbox = _checked(MailboxTable, raw.get("mailbox", {}), ("mailbox",), problems)
    for key in ("credentials", "ca"):
        named = getattr(mailbox, key, None)
        if named is not None and not (directory / named).is_file():
            problems.at(("mailbox", key), f"no such file: {named}")
    opcua = _checked(OpcuaTable, raw.get("opcua", {}), ("opcua",), problems)
    users = opcua.users if opcua is not None and opcua.listen else None
    if users is not None and not (directory / users).is_file():
        problems.at(
            ("opcua", "users"), f"no such file: {users} (add a user: cellctl opcua adduser NAME)"
        )
    machines: dict[str, MachineConfig] = {}
    for name, entry in _entries(raw, "machines", problems).items():
        table = _checked(MachineTable, entry, ("machines", name), problems)
        if table is None:
            continue
        kind = registry.kind(table.kind)
        if _checked(kind.options, table.options, ("machines", name, "options"), problems) is None:
            continue
        if kind.needs_setup and table.setup is None:
            problems.at(("machines", name, "setup"), "a mill needs its setup program")
            continue
        machines[name] = MachineConfig(
            name=name,
            kind=table.kind,
            link=table.link,
            line=LineSettings.parse(table.line or kind.line),
            options=dict(table.options),
            setup=directory / table.setup if table.setup else None,
            go_output=table.go_output,
        )
    cell_value = raw.get("cell")
    cell_raw: dict[str, Any] = cell_value if isinstance(cell_value, dict) else {}
    robot_name = cell.robot if cell else _text(cell_raw.get("robot"))
    robot_kinds_ = robot_kinds()
    mill_kinds_ = mill_kinds()
    robot_name = robot_name or next(
        (n for n, m in machines.items() if m.kind in robot_kinds_), None
    )
    robot = machines.get(robot_name or "")
    if robot is None or robot.kind not in robot_kinds_:
        problems.at(
            ("cell", "robot"),
            f"no robot machine {robot_name!r} of kind {'/'.join(robot_kinds_) or '(none)'}",
        )
    mill_names = (cell.mills if cell else _texts(cell_raw.get("mills"))) or [
        n for n, m in machines.items() if m.kind in mill_kinds_
    ]
    mills = []
    for n in mill_names:
        m = machines.get(n)
        if m is None or m.kind not in mill_kinds_:
            problems.at(
                ("cell", "mills"), f"{n!r} is not a mill ({', '.join(mill_kinds_)} machine)"
            )
        else:
            mills.append(m)
    for m in mills:
        if m.setup is not None:
            _check_program(m, m.setup, ProgramRole.SETUP, problems.items)
    plc_raw = raw.get("plc", {})
    plc: dict[str, Any] = {}
    if not isinstance(plc_raw, dict):
        problems.at(("plc",), f"must be a table, not {type(plc_raw).__name__}")
    else:
        plc = plc_raw
        _check_plc(plc, mills, problems.items)
    robot_programs: dict[str, Any] = {}
    # The robot's kind compiles them; with no usable robot (told above), still check them with
    # the first robot kind's language, so a bad program is not hidden behind another problem.
    robot_kind = (
        registry.kind(robot.kind)
        if robot is not None and robot.kind in robot_kinds_
        else next(iter(registry.kinds("robot")), None)
    )
    sources = _entries(raw, "robot_programs", problems)
    for prog_name, rel in sources.items():
        if not isinstance(rel, str) or not rel:
            problems.at(("robot_programs", prog_name), f"must be a file path, not {rel!r}")
            continue
        path = directory / rel
        language = robot_kind.language if robot_kind is not None else None
        if language is None or language.compile is None:
            continue  # no robot (told above), or one that takes no programs from the host
        try:
            source = path.read_text(encoding="utf-8")
            robot_programs[prog_name] = language.compile(source, prog_name, str(path))
        except OSError as e:
            problems.add(f"[robot_programs] {prog_name}: {path}: {e.strerror}")
        except UnicodeDecodeError as e:
            problems.add(f"[robot_programs] {prog_name}: {path}: not UTF-8 text: {e.reason}")
        except CellctlError as e:
            problems.add(f"[robot_programs] {prog_name}: {e}")
    _check_sizes(raw, cell_raw, directory, problems)
    parts: dict[str, PartType] = {}
    for part_name, entry in _entries(raw, "parts", problems).items():
        part_table = _checked(PartTable, entry, ("parts", part_name), problems)
        if part_table is None:
            continue
        part = _part(directory, part_name, part_table, {m.name: m for m in mills}, problems)
        if part is None:
            continue
        parts[part_name] = part
        for t in part.transfers():
            if t not in sources:
                problems.add(f"[parts.{part_name}] needs robot program {t!r} in [robot_programs]")
    if not parts:
        problems.add("[parts]: no part types: the cell has nothing to make")
    if (
        robot is None
        or cell is None
        or api is None
        or mailbox is None
        or opcua is None
        or problems.items
    ):
        return None, problems.items
    return (
        CellConfig(
            directory=directory,
            name=cell.name or directory.name,
            robot=robot,
            mills=mills,
            plc=plc,
            robot_programs=robot_programs,
            parts=parts,
            poll_period=cell.poll_period,
            raw=raw,
            api_listen=api.listen,
            api_allow_remote=api.allow_remote,
            api=api,
            mailbox=mailbox,
            opcua=opcua,
        ),
        problems.items,
    )


def _text(value: Any) -> str | None:
    return value if isinstance(value, str) and value else None


def _texts(value: Any) -> list[str] | None:
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return value
    return None


def load_cell(directory: Path | str) -> CellConfig:
    """The checked cell config; UsageError listing every problem otherwise."""
    config, problems = check_cell(directory)
    if config is None:
        raise UsageError(f"{Path(directory) / 'cell.toml'}: " + "; ".join(problems))
    return config


def _check_program(
    machine: MachineConfig, path: Path, role: ProgramRole, problems: list[str]
) -> tuple[int, float] | None:
    """Check ``path`` in ``machine``'s program language: its lines and machining time, or None
    after adding its problems."""
    kind: MachineKind = registry.kind(machine.kind)
    if kind.language is None:
        return (0, 0.0)
    checked = kind.language.check(path, role, kind.checked_options(machine.options))
    problems.extend(checked.problems)
    return None if checked.problems else (checked.lines, checked.machining_s)


def _check_plc(plc: dict[str, Any], mills: list[MachineConfig], problems: list[str]) -> None:
    if not plc:
        problems.append("[plc]: missing (url of the cell's Modbus/TCP PLC)")
        return
    if not plc.get("url"):
        problems.append("[plc] url: missing")
    try:
        from cellctl.protocol.plc import PlcMap, canonical

        plc_map = PlcMap.from_toml(plc)
    except CellctlError as e:
        problems.append(f"[plc]: {e}")
        return
    for m in mills:
        if m.go_output is not None and canonical(m.go_output) not in plc_map.coils:
            problems.append(f"[machines.{m.name}] go_output: no PLC coil {m.go_output!r}")


def _part(
    directory: Path,
    name: str,
    table: PartTable,
    mills: dict[str, MachineConfig],
    problems: _Problems,
) -> PartType | None:
    route: list[RouteStep] = []
    for i, step in enumerate(table.route):
        if step.mill not in mills:
            problems.at(("parts", name, "route", i, "mill"), f"unknown mill {step.mill!r}")
            continue
        path = directory / step.program
        if not path.is_file():
            problems.at(("parts", name, "route", i, "program"), f"{path}: no such file")
            continue
        result = _check_program(mills[step.mill], path, ProgramRole.MILLING, problems.items)
        if result is None:
            continue
        lines, seconds = result
        route.append(RouteStep(step.mill, path, path.stem, lines, seconds))
    if len(route) != len(table.route):
        return None
    return PartType(name, tuple(route))
