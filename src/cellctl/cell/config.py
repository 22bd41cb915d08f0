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

    [robot_programs]                      # the robot kind's source of each program
    conveyor_to_cnc1 = "robot/conveyor_to_cnc1.aml"
    cnc1_to_cnc2 = "robot/cnc1_to_cnc2.aml"
    cnc2_to_conveyor = "robot/cnc2_to_conveyor.aml"
    open_vise_cnc1 = "robot/open_vise_cnc1.aml"   # optional: after a part is taken out
    open_vise_cnc2 = "robot/open_vise_cnc2.aml"   # by hand (cellctl.cell.vises)

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

import itertools
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cellctl.cell.configproblems import _checked, _entries, _load_toml, _Problems
from cellctl.cell.configschema import (
    MAX_MACHINES,
    MAX_NAME,
    MAX_PART_TYPES,
    ApiTable,
    CellFile,
    CellTable,
    MachineTable,
    MailboxTable,
    OpcuaTable,
    PartTable,
    RouteStepTable,
    Seconds,
    Text,
    reference_table,
)
from cellctl.errors import CellctlError, UsageError, unknown_machine
from cellctl.files import read_text
from cellctl.kinds import registry
from cellctl.kinds.kind import MachineKind, ProgramRole
from cellctl.link import LineSettings

__all__ = [
    "CONVEYOR",
    "MAX_MACHINES",
    "MAX_NAME",
    "MAX_PART_TYPES",
    "ApiTable",
    "CellConfig",
    "CellFile",
    "CellTable",
    "MachineConfig",
    "MachineTable",
    "MailboxTable",
    "OpcuaTable",
    "PartTable",
    "PartType",
    "RouteStep",
    "RouteStepTable",
    "Seconds",
    "Text",
    "check_cell",
    "load_cell",
    "machine_problems",
    "mill_kinds",
    "open_vise_name",
    "reference_table",
    "refuse_machine",
    "robot_kinds",
    "transfer_ends",
    "transfer_name",
]

#: Where a part can be; the conveyor is where parts come from and go back to.
CONVEYOR = "conveyor"


def robot_kinds() -> tuple[str, ...]:
    """The installed kinds of the robot family (from the registry)."""
    return registry.names("robot")


def mill_kinds() -> tuple[str, ...]:
    """The installed kinds of the mill family (from the registry)."""
    return registry.names("mill")


def mill_names(listed: Any, kinds: Mapping[str, Any]) -> list[str]:
    """The cell's mills: ``[cell] mills`` as ``listed`` (a list of names), else every machine
    of ``kinds`` (name -> kind) whose kind is of the mill family, in their order."""
    return _texts(listed) or [n for n, k in kinds.items() if k in mill_kinds()]


def transfer_name(source: str, target: str) -> str:
    """The robot program that moves a part from ``source`` to ``target``: ``cnc1_to_cnc2``."""
    return f"{source}{_TO}{target}"


def open_vise_name(mill: str) -> str:
    """The robot program that opens ``mill``'s vise with nothing in it: ``open_vise_cnc1``
    (optional: run after the operator took a scrapped part out; docs/cell.md)."""
    return f"open_vise_{mill}"


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
        raise unknown_machine(name, [m.name for m in [self.robot, *self.mills]])


# --- reading and checking (the schema: configschema; the problems: configproblems) ---------


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
    told: set[str] = set()  # machines whose own table has problems (said): no follow-on ones
    for name, entry in _entries(raw, "machines", problems).items():
        table = _checked(MachineTable, entry, ("machines", name), problems)
        if table is None:
            told.add(name)
            continue
        kind = registry.kind(table.kind)
        # A bad option or a missing setup is said here; the machine stays known with its kind,
        # so that the rest (mills, routes, its programs) is checked on, with the kind's
        # default options in place of bad ones.
        options_ok = (
            _checked(kind.options, table.options, ("machines", name, "options"), problems)
            is not None
        )
        if kind.needs_setup and table.setup is None:
            problems.at(("machines", name, "setup"), "a mill needs its setup program")
        machines[name] = MachineConfig(
            name=name,
            kind=table.kind,
            link=table.link,
            line=LineSettings.parse(table.line or kind.line),
            options=dict(table.options) if options_ok else {},
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
    if robot_name in told:
        pass  # its [machines.NAME] table's problems are said above
    elif robot is None or robot.kind not in robot_kinds_:
        problems.at(
            ("cell", "robot"),
            f"no robot machine {robot_name!r} of kind {'/'.join(robot_kinds_) or '(none)'}",
        )
    listed = cell.mills if cell else cell_raw.get("mills")
    mills = []
    for n in mill_names(listed, {n: m.kind for n, m in machines.items()}):
        m = machines.get(n)
        if m is not None and m.kind in mill_kinds_:
            mills.append(m)
        elif n in told:
            continue  # its [machines.NAME] table's problems are said above
        elif m is None:
            problems.at(("cell", "mills"), f"{n!r}: no such machine in [machines]")
        else:
            problems.at(
                ("cell", "mills"),
                f"{n!r} (kind {m.kind}) is not a mill (mill kinds: {', '.join(mill_kinds_)})",
            )
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
            source = read_text(path)
            robot_programs[prog_name] = language.compile(source, prog_name, str(path))
        except OSError as e:
            problems.add(f"[robot_programs] {prog_name}: {path}: {e.strerror}")
        except UnicodeDecodeError as e:
            problems.add(f"[robot_programs] {prog_name}: {path}: not UTF-8 text: {e.reason}")
        except CellctlError as e:
            problems.add(f"[robot_programs] {prog_name}: {e}")
    _check_sizes(raw, cell_raw, directory, problems)
    parts: dict[str, PartType] = {}
    declared = _entries(raw, "parts", problems)
    for part_name, entry in declared.items():
        part_table = _checked(PartTable, entry, ("parts", part_name), problems)
        if part_table is None:
            continue
        part = _part(directory, part_name, part_table, {m.name: m for m in mills}, told, problems)
        if part is None:
            continue
        parts[part_name] = part
        for t in part.transfers():
            if t not in sources:
                problems.add(f"[parts.{part_name}] needs robot program {t!r} in [robot_programs]")
    # Only when none is declared: a declared part type with problems has them told above.
    if not declared and isinstance(raw.get("parts", {}), dict):
        problems.add("[parts]: no part types: the cell has nothing to make")
    for prog_name in sources:
        opened = prog_name.removeprefix(open_vise_name(""))
        # A machine whose own table has problems (told above) is no mill yet: not again here.
        if opened != prog_name and opened not in {m.name for m in mills} | told:
            problems.add(
                f"[robot_programs] {prog_name}: no mill {opened!r} (open_vise_<mill> opens "
                f"that mill's vise; mills: {', '.join(m.name for m in mills)})"
            )
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


def machine_problems(directory: Path | str, name: str) -> list[str]:
    """The problems of ``[machines.NAME]`` alone, in the words (and with the line) of
    ``cellctl cell check``: a command about that one machine refuses it as the check says it.
    Empty if its table is sound (or there is none: the caller says so)."""
    raw, text = _load_toml(Path(directory))
    problems = _Problems(text)
    entry = _entries(raw, "machines", problems).get(name)
    if entry is not None:
        _checked(MachineTable, entry, ("machines", name), problems)
    return problems.items


def refuse_machine(directory: Path | str, name: str) -> None:
    """UsageError with :func:`machine_problems` (the file named once), if there are any."""
    problems = machine_problems(directory, name)
    if problems:
        raise UsageError(f"{Path(directory) / 'cell.toml'}: " + "; ".join(problems))


def load_cell(directory: Path | str) -> CellConfig:
    """The checked cell config; UsageError listing every problem otherwise."""
    config, problems = check_cell(directory)
    if config is None:
        path = f"{Path(directory) / 'cell.toml'}: "
        said = "; ".join(problems)
        raise UsageError(said if said.startswith(path) else path + said)  # the path once
    return config


def _check_program(
    machine: MachineConfig, path: Path, role: ProgramRole, problems: list[str]
) -> tuple[int, float] | None:
    """Check ``path`` in ``machine``'s program language: its lines and machining time, or None
    after adding its problems."""
    kind: MachineKind = registry.kind(machine.kind)
    if kind.language is None:
        return (0, 0.0)
    try:
        options = kind.checked_options(machine.options)
    except UsageError:
        return None  # options it cannot do without, told with the machine's table
    checked = kind.language.check(path, role, options)
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
    told: set[str],
    problems: _Problems,
) -> PartType | None:
    route: list[RouteStep] = []
    for i, step in enumerate(table.route):
        if step.mill in told:
            continue  # a machine whose own table's problems are said: not a second time here
        if step.mill not in mills:
            problems.at(("parts", name, "route", i, "mill"), f"unknown mill {step.mill!r}")
            continue
        path = directory / step.program
        if not path.exists():  # anything else there: the kind's check says what it is
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
