"""What the console knows of a cell before and beside the API: its machines (in cell.toml
order, with the source's menu titles), how to open it, and checking a dialog's parameters
before anything is sent.

::

    client = await open_console_cell(Path("cell"))     # attached or standalone
    machines = cell_machines(Path("cell"))              # [ConsoleMachine("robot", "robot", ...)]
    machines = status_machines(snapshot)                # a server's own (no cell.toml)
    params = check_params(machine, fn, {"partition": "6"}, Path("cell"))   # UsageError
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from cellctl.cell.owner import controller_holder
from cellctl.errors import CellctlError, UsageError
from cellctl.kinds import registry
from cellctl.kinds.kind import FAMILIES, MachineKind
from cellctl.service.client import CellClient, open_cell
from cellctl.service.functions import MachineFunction, family_of_kind, kind_menu
from cellctl.service.machines import MachineRef, load_cell_file, resolve_machine
from cellctl.ui.calls import read_program


def picked_files(kind: MachineKind) -> tuple[str, ...]:
    """A kind's files for its program pickers: what it sends, then the sources it compiles."""
    language = kind.language
    sources = (language.suffix,) if language is not None and language.compile else ()
    return tuple(dict.fromkeys((*kind.picked_files, *sources)))


#: File name endings a family's program picker shows (every kind's of that family).
PROGRAM_SUFFIXES: dict[str, tuple[str, ...]] = {
    family: tuple(dict.fromkeys(s for k in registry.kinds(family) for s in picked_files(k)))
    for family in FAMILIES
}
#: Dialog fields typed as text that the functions take as whole numbers.
_WHOLE_NUMBERS = (int,)


@dataclass(frozen=True)
class ConsoleMachine:
    """A machine of the cell as the console's menus show it."""

    name: str
    family: str  # "robot" or "mill"
    title: str  # the source's menu title: ROBOT, NC MACHINE #1 ...
    options: dict[str, Any] = field(default_factory=dict)
    setup: str | None = None  # the mill's setup program (cell.toml), relative to the cell
    kind: str | None = None  # cell.toml's kind (None: the first of its family with the function)

    @property
    def suffixes(self) -> tuple[str, ...]:
        """The file endings its program picker shows: what its functions send, and the
        sources its kind compiles into that on the way (a robot's .rec and .aml)."""
        if self.kind is None:
            return PROGRAM_SUFFIXES.get(self.family, ())
        return picked_files(registry.kind(self.kind))


def cell_machines(directory: Path) -> list[ConsoleMachine]:
    """Every robot and mill of the cell's ``cell.toml``, in the file's order."""
    entries = load_cell_file(directory).get("machines", {})
    if not isinstance(entries, dict):
        raise UsageError(f"{directory / 'cell.toml'}: [machines] must be a table")
    found: list[ConsoleMachine] = []
    families = [
        family_of_kind(str(e.get("kind", ""))) for e in entries.values() if isinstance(e, dict)
    ]
    titles = _titles(families)
    for name, entry in entries.items():
        family = family_of_kind(str(entry.get("kind", ""))) if isinstance(entry, dict) else None
        if family is None:
            # A kind not installed (a typo): refused as `cellctl cell check` says it, never a
            # menu without that machine.
            from cellctl.cell.config import refuse_machine

            refuse_machine(directory, name)
            continue
        setup = entry.get("setup")
        found.append(
            ConsoleMachine(
                name,
                family,
                next(titles[family]),
                dict(entry.get("options", {})),
                str(setup) if isinstance(setup, str) else None,
                str(entry["kind"]),
            )
        )
    if not found:
        raise UsageError(f"no robot or mill in {directory / 'cell.toml'}")
    return found


def _titles(families: list[str | None]) -> dict[str, Iterator[str]]:
    """The source's menu titles, in order, per family: ROBOT (#1, #2 ... when there are
    several), NC MACHINE #1, #2 ..."""
    one_robot = families.count("robot") == 1
    robots = (f"ROBOT #{n}" if not one_robot else "ROBOT" for n in itertools.count(1))
    return {"robot": robots, "mill": (f"NC MACHINE #{n}" for n in itertools.count(1))}


def status_machines(snapshot: dict[str, Any]) -> list[ConsoleMachine]:
    """The robots and mills of a status snapshot (a server's own machines, where the
    directory has no cell.toml), in its order; a kind not installed here has none of its
    own (the family's program files are offered)."""
    rows = [m for m in snapshot.get("machines", {}).values() if isinstance(m, dict)]
    rows = [m for m in rows if m.get("family") in ("robot", "mill")]
    titles = _titles([str(m["family"]) for m in rows])
    return [
        ConsoleMachine(
            str(m.get("name", "")),
            str(m["family"]),
            next(titles[str(m["family"])]),
            kind=str(m["kind"]) if family_of_kind(str(m.get("kind", ""))) else None,
        )
        for m in rows
    ]


def cell_refs(directory: Path) -> dict[str, MachineRef]:
    """The links of every machine of the cell (what a standalone console opens)."""
    return {
        m.name: resolve_machine(directory, m.family, name=m.name, link=None)
        for m in cell_machines(directory)
    }


def is_cell(directory: Path) -> bool:
    """Whether ``directory`` is a cell (it has a cell.toml), not only a server's directory."""
    return (directory / "cell.toml").is_file()


async def open_console_cell(directory: Path, server: str | None = None) -> CellClient:
    """The running controller's API, or the cell's machines from this process; on a
    directory without a cell.toml, the API of the server running there (its machines are
    what its status shows). ``server``: what configures such a directory and how to start
    its server (``a dnc.toml (...): start it with `cellctl dnc serve --dir shop```), said
    when none runs there."""
    if not is_cell(directory):
        if controller_holder(directory) is None:
            if server is not None:
                raise UsageError(f"no server runs on {directory}: it has no cell.toml but {server}")
            raise UsageError(
                f"no cell in {directory}: {directory / 'cell.toml'} is missing, "
                "and no server runs there"
            )
        return await open_cell(directory, {})
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


def machine_kind(machine: ConsoleMachine, fn: MachineFunction) -> MachineKind:
    """The kind of ``machine`` (without one, the first kind of its family that has ``fn``)."""
    if machine.kind is not None:
        return registry.kind(machine.kind)
    for kind in registry.kinds(machine.family):
        if any(f.name == fn.name for f in kind_menu(kind.name)):
            return kind
    raise UsageError(f"no {machine.family} kind has a function {fn.name!r}")


def compiled_program(
    machine: ConsoleMachine, fn: MachineFunction, path: Path, program: dict[str, str]
) -> dict[str, str]:
    """``program`` as the function sends it: a source its kind compiles (a robot's .aml) is
    compiled on the way, named as the compiled file would be (``load1.rec``); the compiler's
    problems are a UsageError. Any other file goes as it is."""
    kind = machine_kind(machine, fn)
    language = kind.language
    if (
        language is None
        or language.compile is None
        or path.suffix.lower() != language.suffix
        or path.suffix.lower() in kind.picked_files
    ):
        return program
    try:
        compiled = language.compile(program["text"], path.stem, program["program"])
    except CellctlError as e:
        raise UsageError(str(e)) from None
    to_text = getattr(compiled, "to_text", None)
    if not callable(to_text):
        raise UsageError(f"{program['program']}: {kind.name} cannot send a compiled program")
    sent = kind.picked_files[0] if kind.picked_files else ""
    return {"program": path.stem + sent, "text": str(to_text())}


def check_program(
    machine: ConsoleMachine, fn: MachineFunction, program: dict[str, str]
) -> list[str]:
    """Every problem of a program, one per line (empty: it may be sent), as its kind checks
    what that function sends."""
    kind = machine_kind(machine, fn)
    if kind.check_text is None:
        return []
    try:
        options = kind.checked_options(machine.options)
    except UsageError as e:
        return [str(e)]
    return kind.check_text(fn.name, program["program"], program["text"], options)


def _field_problems(
    fn: MachineFunction, params: dict[str, Any], skip: tuple[str, ...]
) -> list[str]:
    """What the function's own check says of the answers in ``params`` (a partition out of
    range), leaving out the fields in ``skip`` and the ones not given."""
    try:
        fn.params.model_validate(params)
    except ValidationError as e:
        return [
            str(item["msg"]).removeprefix("Value error, ")
            for item in e.errors(include_url=False, include_input=False)
            if item["type"] != "missing" and (not item["loc"] or item["loc"][0] not in skip)
        ]
    return []


def check_params(
    machine: ConsoleMachine, fn: MachineFunction, raw: dict[str, Any], directory: Path
) -> dict[str, Any]:
    """A dialog's answers as the function's parameters; UsageError (one problem a line)
    when anything is wrong, before a byte is sent."""
    fields = fn.params.model_fields
    params: dict[str, Any] = {}
    problems: list[str] = []
    for key, info in fields.items():
        # A number typed in a text field: the function's own check says what range it takes.
        if info.annotation in _WHOLE_NUMBERS and (key in raw or info.is_required()):
            text = str(raw.get(key, "")).strip()
            if text.isascii() and text.isdecimal():
                params[key] = int(text)
            else:
                problems.append(f"{key} must be a whole number, not {text or 'nothing'}")
    if "program" in fields:
        try:
            path, program = read_program_file(str(raw.get("program", "")), directory)
            program = compiled_program(machine, fn, path, program)
        except UsageError as e:
            problems.append(str(e))
        else:
            problems += check_program(machine, fn, program)
            params.update(program)
    for key in ("force", "on"):  # a checkbox: ticked or not
        if key in fields:
            params[key] = bool(raw.get(key, False))
    if not problems:
        try:
            fn.check(params)
        except UsageError as e:
            problems.append(str(e))
    else:  # the other answers' problems beside the file's: all told at once
        problems += _field_problems(fn, params, skip=("program", "text"))
    if problems:
        raise UsageError("\n".join(problems))
    return params
