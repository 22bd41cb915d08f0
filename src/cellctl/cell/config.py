"""The cell described in one file: ``cell.toml`` in the cell directory.

::

    [cell]
    name = "CIM laboratory machining cell"
    robot = "robot"                       # the machine that tends the mills
    mills = ["cnc1", "cnc2"]              # in route order: CNC 1 roughing, CNC 2 finishing
    poll_period = 0.5                     # s: a fault is noticed within one poll period

    [machines.robot]
    kind = "ibm7545"
    link = "rfc2217://127.0.0.1:7001"
    line = "4800,7E2"

    [machines.cnc1]
    kind = "dyna2400"
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

import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cellctl.errors import CellctlError, UsageError
from cellctl.link import LineSettings
from cellctl.protocol import dynalan
from cellctl.protocol.aml import compile_source
from cellctl.protocol.robot import ProgramFile

#: Where a part can be; the conveyor is where parts come from and go back to.
CONVEYOR = "conveyor"

ROBOT_KINDS = ("ibm7545", "ibm7547")
MILL_KINDS = ("dyna2400",)
DEFAULT_LINES = {"ibm7545": "4800,7E2", "ibm7547": "4800,7E2", "dyna2400": "4800,7E2"}


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
    robot_programs: dict[str, ProgramFile]
    parts: dict[str, PartType]
    poll_period: float = 0.5
    raw: dict[str, Any] = field(default_factory=dict)

    def machine(self, name: str) -> MachineConfig:
        """The robot or mill called ``name``."""
        for m in [self.robot, *self.mills]:
            if m.name == name:
                return m
        raise UsageError(f"unknown machine {name!r}")


def _load_toml(directory: Path) -> dict[str, Any]:
    import tomllib

    path = directory / "cell.toml"
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise UsageError(
            f"{path}: no such file (create it, or run 'cellctl emulate cell')"
        ) from None
    except tomllib.TOMLDecodeError as e:
        raise UsageError(f"{path}: not valid TOML: {e}") from None


def check_cell(directory: Path | str) -> tuple[CellConfig | None, list[str]]:
    """Read and check ``<directory>/cell.toml``; return the config (if usable) and problems."""
    directory = Path(directory)
    problems: list[str] = []
    try:
        raw = _load_toml(directory)
    except UsageError as e:
        return None, [str(e)]
    cell = raw.get("cell", {})
    machines_raw: dict[str, Any] = raw.get("machines", {})
    machines: dict[str, MachineConfig] = {}
    for name, entry in machines_raw.items():
        m = _machine(directory, name, entry, problems)
        if m is not None:
            machines[name] = m
    robot_name = cell.get("robot") or next(
        (n for n, m in machines.items() if m.kind in ROBOT_KINDS), None
    )
    mill_names: list[str] = cell.get("mills") or [
        n for n, m in machines.items() if m.kind in MILL_KINDS
    ]
    robot = machines.get(robot_name or "")
    if robot is None or robot.kind not in ROBOT_KINDS:
        problems.append(f"[cell] robot: no robot machine {robot_name!r} of kind ibm7545/ibm7547")
    mills = []
    for n in mill_names:
        m = machines.get(n)
        if m is None or m.kind not in MILL_KINDS:
            problems.append(f"[cell] mills: {n!r} is not a dyna2400 machine")
        else:
            mills.append(m)
    for m in mills:
        if m.setup is not None:
            _check_dynalan(m.setup, problems, role=dynalan.ProgramRole.SETUP)
    plc = raw.get("plc", {})
    _check_plc(plc, mills, problems)
    robot_programs: dict[str, ProgramFile] = {}
    for prog_name, rel in raw.get("robot_programs", {}).items():
        path = directory / rel
        try:
            text = path.read_text(encoding="utf-8")
            app = prog_name.upper().replace("_", "")[:8]
            robot_programs[prog_name] = compile_source(text, app, 1, source=str(path))
        except OSError as e:
            problems.append(f"[robot_programs] {prog_name}: {path}: {e.strerror}")
        except CellctlError as e:
            problems.append(f"[robot_programs] {prog_name}: {e}")
    parts: dict[str, PartType] = {}
    for part_name, entry in raw.get("parts", {}).items():
        part = _part(directory, part_name, entry, {m.name for m in mills}, problems)
        if part is None:
            continue
        parts[part_name] = part
        for t in part.transfers():
            if t not in raw.get("robot_programs", {}):
                problems.append(
                    f"[parts.{part_name}] needs robot program {t!r} in [robot_programs]"
                )
    if not parts:
        problems.append("[parts]: no part types: the cell has nothing to make")
    poll = float(cell.get("poll_period", 0.5))
    if poll <= 0:
        problems.append("[cell] poll_period must be positive")
    if robot is None or problems:
        return None, problems
    return (
        CellConfig(
            directory=directory,
            name=str(cell.get("name", directory.name)),
            robot=robot,
            mills=mills,
            plc=plc,
            robot_programs=robot_programs,
            parts=parts,
            poll_period=poll,
            raw=raw,
        ),
        problems,
    )


def load_cell(directory: Path | str) -> CellConfig:
    """The checked cell config; UsageError listing every problem otherwise."""
    config, problems = check_cell(directory)
    if config is None:
        raise UsageError(f"{Path(directory) / 'cell.toml'}: " + "; ".join(problems))
    return config


def _machine(directory: Path, name: str, entry: Any, problems: list[str]) -> MachineConfig | None:
    where = f"[machines.{name}]"
    if not isinstance(entry, dict):
        problems.append(f"{where}: must be a table")
        return None
    kind = entry.get("kind")
    if kind not in DEFAULT_LINES:
        problems.append(f"{where} kind: {kind!r} is not one of {', '.join(DEFAULT_LINES)}")
        return None
    link = entry.get("link")
    if not link:
        problems.append(f"{where} link: missing (a device path, socket://, rfc2217://)")
        return None
    try:
        line = LineSettings.parse(str(entry.get("line", DEFAULT_LINES[kind])))
    except UsageError as e:
        problems.append(f"{where} line: {e}")
        return None
    setup = None
    if kind in MILL_KINDS:
        if entry.get("setup"):
            setup = directory / str(entry["setup"])
        else:
            problems.append(f"{where} setup: a mill needs its setup program")
    return MachineConfig(
        name=name,
        kind=kind,
        link=str(link),
        line=line,
        options=dict(entry.get("options", {})),
        setup=setup,
        go_output=entry.get("go_output"),
    )


def _check_dynalan(
    path: Path, problems: list[str], role: dynalan.ProgramRole = dynalan.ProgramRole.AUTO
) -> dynalan.Validation | None:
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as e:
        problems.append(f"{path}: cannot read: {e}")
        return None
    program = dynalan.parse_program(text, name=path.name)
    result = dynalan.validate(program, dynalan.ValidationContext(role=role))
    problems.extend(p.format(str(path)) for p in result.errors)
    return result


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
    directory: Path, name: str, entry: Any, mills: set[str], problems: list[str]
) -> PartType | None:
    where = f"[parts.{name}]"
    route_raw = entry.get("route") if isinstance(entry, dict) else None
    if not route_raw:
        problems.append(f"{where} route: missing (a list of {{ mill, program }})")
        return None
    route: list[RouteStep] = []
    for i, step in enumerate(route_raw, start=1):
        mill = step.get("mill")
        if mill not in mills:
            problems.append(f"{where} route step {i}: unknown mill {mill!r}")
            continue
        if not step.get("program"):
            problems.append(f"{where} route step {i}: missing program")
            continue
        path = directory / str(step["program"])
        result = _check_dynalan(path, problems, role=dynalan.ProgramRole.MILLING)
        if result is None or not result.ok:
            continue
        seconds = result.toolpath.machining_seconds if result.toolpath else 0.0
        route.append(RouteStep(mill, path, path.stem, len(result.program.lines), seconds))
    if len(route) != len(route_raw):
        return None
    return PartType(name, tuple(route))
