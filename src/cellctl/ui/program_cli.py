"""``cellctl program check|preview FILE``: a program of any installed machine kind, checked or
drawn by that kind's own language (its :class:`~cellctl.kinds.kind.ProgramLanguage` hooks),
before it goes near a machine::

    cellctl program check part.nc robot/load.aml        # every problem; exit 1 on one
    cellctl program check --machine cnc1 rough.dyn      # with cnc1's kind and options
    cellctl program preview part.nc -o part.svg         # the toolpath, as the dashboard draws it

The kind is ``--kind``, else the kind of the cell's ``--machine`` (whose cell.toml options
apply), else the one whose programs end as the file does.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from cellctl.errors import UsageError, unknown_machine, with_article
from cellctl.files import read_file, reason, write_output
from cellctl.ui.common import cell_dir, console, json_option, print_json

if TYPE_CHECKING:
    from pydantic import BaseModel

    from cellctl.kinds.kind import MachineKind, ProgramLanguage, ProgramRole


@click.group("program")
def program_group() -> None:
    """A program file of any machine kind: check it, draw its toolpath."""


KIND_HELP = (
    "The kind whose language it is (`cellctl kinds`; default: by --machine, else by the "
    "file's ending)."
)
MACHINE_HELP = "The cell's machine whose kind and cell.toml options apply."


def language_for(
    ctx: click.Context, path: Path, kind_name: str | None, machine: str | None
) -> tuple[MachineKind, ProgramLanguage, BaseModel]:
    """The kind ``path`` is a program of, its language and the options it is checked with.

    Refused in words (UsageError): a machine the cell does not have, a ``--kind`` that is not
    the machine's, a kind without a program language, an ending no kind's programs have or
    that several kinds read differently."""
    from cellctl.kinds import registry
    from cellctl.service.machines import load_cell_file

    options: dict[str, object] = {}
    if machine is not None:
        directory = cell_dir(ctx)
        machines = load_cell_file(directory).get("machines", {})
        if machine not in machines:
            raise unknown_machine(machine, machines, str(directory / "cell.toml"))
        entry = machines[machine]
        named = str(entry.get("kind", ""))
        if kind_name is not None and kind_name != named:
            raise UsageError(f"--kind {kind_name}: {machine} is {with_article(named)} in cell.toml")
        kind_name, options = named, dict(entry.get("options", {}))
    kind = registry.kind(kind_name) if kind_name else _by_ending(path, registry.kinds())
    if kind.language is None:
        raise UsageError(f"{with_article(kind.title)} has no program language to check")
    return kind, kind.language, kind.checked_options(options)


def _by_ending(path: Path, kinds: list[MachineKind]) -> MachineKind:
    suffix = path.suffix.lower()
    readers = [k for k in kinds if k.language is not None and k.language.suffix == suffix]
    # Kinds that share one language (a robot model and its sibling) read a file alike.
    checks = {id(k.language.check) for k in readers if k.language is not None}
    if len(checks) == 1:
        return readers[0]
    if readers:
        names = ", ".join(k.name for k in readers)
        raise UsageError(f"{path}: {suffix} programs are read by {names}: say which (--kind)")
    endings = sorted({f"{k.language.suffix} {k.name}" for k in kinds if k.language is not None})
    raise UsageError(
        f"{path}: no installed kind's programs end in {suffix or 'nothing'} "
        f"(known: {', '.join(endings)}); say --kind"
    )


def _role(kind: MachineKind, role: str | None) -> ProgramRole:
    """``--role``, else what a program of ``kind`` is for: a robot's a transfer, any other's
    a cut."""
    from cellctl.kinds.kind import ProgramRole

    if role:
        return ProgramRole(role)
    return ProgramRole.TRANSFER if kind.family == "robot" else ProgramRole.MILLING


def _existing(path: Path) -> Path:
    """``path``, a regular file; else refused with what it is, in the words of every reader
    of a file (``read_file`` refuses a directory or a device by its type, before opening it:
    "a character device, not a regular file")."""
    if path.is_file():
        return path
    if not path.exists():
        raise UsageError(f"{path}: no such file")
    try:
        read_file(path, limit=0)
    except OSError as e:
        raise UsageError(f"{path}: {reason(e)}") from None
    return path  # a regular file by now: its kind's check reads it


def _duration(seconds: float) -> str:
    whole = round(seconds)
    return f"{whole // 3600}:{whole % 3600 // 60:02d}:{whole % 60:02d}"


@program_group.command("check")
@click.argument("files", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--kind", "kind_name", metavar="KIND", help=KIND_HELP)
@click.option("--machine", metavar="NAME", help=MACHINE_HELP)
@click.option(
    "--role",
    type=click.Choice(["setup", "milling", "transfer"]),
    help="What it is for (default: transfer for a robot's, milling for any other's).",
)
@json_option
@click.pass_context
def check_command(
    ctx: click.Context,
    files: tuple[Path, ...],
    kind_name: str | None,
    machine: str | None,
    role: str | None,
    as_json: bool,
) -> None:
    """Check each FILE as its kind's controller would take it: every problem with its line,
    exit 1 if any file has one; a good one's lines and estimated run time."""
    bad = 0
    found: list[dict[str, object]] = []
    for path in files:
        kind, language, options = language_for(ctx, _existing(path), kind_name, machine)
        checked = language.check(path, _role(kind, role), options)
        bad += 1 if checked.problems else 0
        if as_json:
            found.append(
                {
                    "file": str(path),
                    "kind": kind.name,
                    "ok": checked.ok,
                    "problems": list(checked.problems),
                    "lines": checked.lines,
                    "machining_s": checked.machining_s,
                }
            )
            continue
        for problem in checked.problems:
            console.print(problem, style="red", markup=False, soft_wrap=True)
        if checked.problems:
            what = f"{checked.counted} as {with_article(kind.name)} program"
            console.print(f"{path}: {what}", soft_wrap=True)
            continue
        seconds = checked.machining_s
        estimate = f", est. run time {_duration(seconds)}" if seconds else ""
        good = f"a good {kind.name} program, {checked.lines} line(s){estimate}"
        console.print(f"{path}: {good}", soft_wrap=True)
    if as_json:
        print_json(found)
    sys.exit(1 if bad else 0)


@program_group.command("preview")
@click.argument("file", type=click.Path(path_type=Path))
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Where to draw it (.svg).",
)
@click.option("--kind", "kind_name", metavar="KIND", help=KIND_HELP)
@click.option("--machine", metavar="NAME", help=MACHINE_HELP)
@click.pass_context
def preview_command(
    ctx: click.Context, file: Path, output: Path, kind_name: str | None, machine: str | None
) -> None:
    """Draw FILE's toolpath to an SVG, as the dashboard draws it; a program with problems is
    checked first and refused with them."""
    if output.suffix.lower() != ".svg":
        raise click.BadParameter("the drawing is SVG: the output must end in .svg", param_hint="-o")
    kind, language, options = language_for(ctx, _existing(file), kind_name, machine)
    if language.preview is None:
        raise UsageError(f"{with_article(kind.title)} has no toolpath to draw")
    checked = language.check(file, _role(kind, None), options)
    if checked.problems:
        for problem in checked.problems:
            console.print(problem, style="red", markup=False, soft_wrap=True)
        raise UsageError(f"cannot draw {file}: {checked.counted}")
    drawn = language.preview(file.read_text(encoding="latin-1"), file.name, options)
    try:
        write_output(output, drawn.svg)
    except OSError as e:
        raise UsageError(f"{output}: cannot write: {e.strerror}") from None
    console.print(f"{output}: {file.name} drawn, {drawn.blocks} block(s)", soft_wrap=True)
