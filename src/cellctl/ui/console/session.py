"""What the console knows of a cell before and beside the API: its machines (in cell.toml
order, with the source's menu titles), how to open it, and checking a dialog's parameters
before anything is sent.

::

    client = await open_console_cell(Path("cell"))     # attached or standalone
    machines = cell_machines(Path("cell"))              # [ConsoleMachine("robot", "robot", ...)]
    params = check_params(machine, fn, {"partition": "6"}, Path("cell"))   # UsageError
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cellctl.errors import UsageError
from cellctl.kinds.dyna2400.driver import MillConfig
from cellctl.kinds.dyna2400.dynalan import ProgramRole, Severity, ValidationContext, parse_program
from cellctl.kinds.dyna2400.dynalan import validate as validate_program
from cellctl.kinds.ibm7545.records import PARTITIONS, ProgramFile
from cellctl.service.client import CellClient, open_cell
from cellctl.service.functions import FAMILY_OF_KIND, MachineFunction
from cellctl.service.machines import MachineRef, load_cell_file, resolve_machine
from cellctl.ui.calls import read_program

#: File name endings a family's program picker shows.
PROGRAM_SUFFIXES = {"robot": (".rec",), "mill": (".dyn",)}
#: The role a mill function's program plays (for the validator).
MILL_ROLES = {"init": ProgramRole.SETUP, "download": ProgramRole.MILLING}


@dataclass(frozen=True)
class ConsoleMachine:
    """A machine of the cell as the console's menus show it."""

    name: str
    family: str  # "robot" or "mill"
    title: str  # the source's menu title: ROBOT, NC MACHINE #1 ...
    options: dict[str, Any] = field(default_factory=dict)
    setup: str | None = None  # the mill's setup program (cell.toml), relative to the cell


def cell_machines(directory: Path) -> list[ConsoleMachine]:
    """Every robot and mill of the cell's ``cell.toml``, in the file's order."""
    entries = load_cell_file(directory).get("machines", {})
    if not isinstance(entries, dict):
        raise UsageError(f"{directory / 'cell.toml'}: [machines] must be a table")
    found: list[ConsoleMachine] = []
    counts = {"robot": 0, "mill": 0}
    families = [
        FAMILY_OF_KIND.get(e.get("kind", "")) for e in entries.values() if isinstance(e, dict)
    ]
    for name, entry in entries.items():
        if not isinstance(entry, dict) or entry.get("kind") not in FAMILY_OF_KIND:
            continue
        family = FAMILY_OF_KIND[entry["kind"]]
        counts[family] += 1
        if family == "robot":
            title = "ROBOT" if families.count("robot") == 1 else f"ROBOT #{counts['robot']}"
        else:
            title = f"NC MACHINE #{counts['mill']}"
        setup = entry.get("setup")
        found.append(
            ConsoleMachine(
                name,
                family,
                title,
                dict(entry.get("options", {})),
                str(setup) if isinstance(setup, str) else None,
            )
        )
    if not found:
        raise UsageError(f"no robot or mill in {directory / 'cell.toml'}")
    return found


def cell_refs(directory: Path) -> dict[str, MachineRef]:
    """The links of every machine of the cell (what a standalone console opens)."""
    return {
        m.name: resolve_machine(directory, m.family, name=m.name, link=None)
        for m in cell_machines(directory)
    }


async def open_console_cell(directory: Path) -> CellClient:
    """The running controller's API, or the cell's machines from this process."""
    if not (directory / "cell.toml").is_file():
        raise UsageError(f"no cell in {directory}: {directory / 'cell.toml'} is missing")
    return await open_cell(directory, cell_refs(directory))


def read_program_file(path_text: str, directory: Path) -> tuple[Path, dict[str, str]]:
    """The program a dialog names (relative to the cell directory) as the API takes it."""
    if not path_text.strip():
        raise UsageError("give a program file")
    given = path_text.strip()
    path = Path(given).expanduser()
    if not path.is_absolute():
        path = directory / path
    try:
        return path, read_program(path)
    except UsageError as e:  # named as the operator typed it, not the absolute path
        raise UsageError(str(e).replace(str(path), given, 1)) from None


def check_program(
    machine: ConsoleMachine, fn: MachineFunction, program: dict[str, str]
) -> list[str]:
    """Every problem of a program, one per line (empty: it may be sent)."""
    name, text = program["program"], program["text"]
    if machine.family == "robot":
        try:
            ProgramFile.parse(text, name)
        except UsageError as e:
            return [str(e)]
        return []
    config = MillConfig.from_options(machine.options)
    role = MILL_ROLES.get(fn.name, ProgramRole.AUTO)
    result = validate_program(
        parse_program(text, name=name), ValidationContext(role=role, config=config.machine())
    )
    return [p.format(name) for p in result.problems if p.severity is Severity.ERROR]


def check_params(
    machine: ConsoleMachine, fn: MachineFunction, raw: dict[str, Any], directory: Path
) -> dict[str, Any]:
    """A dialog's answers as the function's parameters; UsageError (one problem a line)
    when anything is wrong, before a byte is sent."""
    fields = fn.params.model_fields
    params: dict[str, Any] = {}
    problems: list[str] = []
    if "partition" in fields:
        text = str(raw.get("partition", "")).strip()
        if not text.isdecimal() or int(text) not in PARTITIONS:
            problems.append(f"partition must be 1 to 5, not {text or 'nothing'} (partition error)")
        else:
            params["partition"] = int(text)
    if "program" in fields:
        try:
            _, program = read_program_file(str(raw.get("program", "")), directory)
        except UsageError as e:
            problems.append(str(e))
        else:
            problems += check_program(machine, fn, program)
            params.update(program)
    if "force" in fields:
        params["force"] = bool(raw.get("force", False))
    if not problems:
        try:
            fn.check(params)
        except UsageError as e:
            problems.append(str(e))
    if problems:
        raise UsageError("\n".join(problems))
    return params
