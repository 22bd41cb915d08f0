"""Pieces every command shares: running a coroutine, one-line errors, exit codes."""

from __future__ import annotations

import asyncio
import json
import logging
import signal
import sys
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any, NoReturn, TypeVar

import click
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from cellctl.errors import CellctlError, UsageError, exit_code
from cellctl.service.machines import MachineRef, resolve_machine

T = TypeVar("T")

console = Console(highlight=False)
err_console = Console(stderr=True, highlight=False)


def run(coro_fn: Callable[[], Coroutine[Any, Any, T]]) -> T:
    """Run a command's coroutine; a CellctlError becomes one line on stderr and an exit code."""
    # The PLC driver turns pymodbus failures into typed errors; pymodbus's own error log
    # (with frame dumps) would only repeat them on the operator's screen.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        return asyncio.run(coro_fn())
    except CellctlError as e:
        fail(e)
    except KeyboardInterrupt:
        err_console.print("interrupted")
        sys.exit(130)


def json_option(f: Callable[..., Any]) -> Callable[..., Any]:
    """``--json``: the listing as one JSON document, for scripts."""
    return click.option(
        "--json", "as_json", is_flag=True, help="Print JSON for scripts instead of a table."
    )(f)


def print_json(data: Any) -> None:
    """``data`` as indented JSON on stdout (ids and texts whole, times as given)."""
    click.echo(json.dumps(data, indent=2, ensure_ascii=False, default=str))


def print_table(table: Table) -> None:
    """A table on a terminal as wide as the terminal; piped, each row whole on one line
    (ids never cut, nothing wrapped at 80 columns) for grep and awk."""
    if console.is_terminal:
        console.print(table)
        return
    table.expand = False
    for column in table.columns:
        column.no_wrap = True
        column.overflow = "ignore"
        column.ratio = None
    wide = Console(file=console.file, width=100_000, highlight=False, no_color=True)
    wide.print(table)


def print_line(text: str) -> None:
    """One line of output, never hard-wrapped (a pipe gets it whole)."""
    console.print(text, markup=False, soft_wrap=True, highlight=False)


def fail(error: CellctlError) -> NoReturn:
    """Print ``error`` as one line on stderr and exit with its code."""
    err_console.print(f"[red]error:[/red] {escape(str(error))}", markup=True, soft_wrap=True)
    sys.exit(exit_code(error))


class CellctlGroup(click.Group):
    """The top group: a typed error raised outside a command's coroutine (reading a file,
    checking an option) is one line and an exit code too, never a traceback."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except CellctlError as e:
            fail(e)


#: Where a command's own ``--cell`` (after the command's name) keeps its value.
_CELL_KEY = "cellctl.cell"

#: Top-level commands that do not take a cell (the factory has its own ``--dir``).
NO_CELL_COMMANDS = frozenset({"factory", "kinds"})


def cell_dir(ctx: click.Context) -> Path:
    """The cell directory chosen with ``--cell`` (before or after the command), or its default.

    Both given and different is refused: which one was meant cannot be guessed."""
    root = ctx.find_root()
    top = root.params.get("cell") or "cell"
    local: str | None = ctx.meta.get(_CELL_KEY)
    if local is None:
        return Path(top)
    source = root.get_parameter_source("cell")
    if source is click.core.ParameterSource.COMMANDLINE and Path(top) != Path(local):
        raise UsageError(
            f"--cell given twice: {top} (before the command) and {local} (after it); give one"
        )
    return Path(local)


def cell_given(ctx: click.Context) -> bool:
    """Whether the cell directory was named (``--cell`` anywhere, or CELLCTL_CELL)."""
    source = ctx.find_root().get_parameter_source("cell")
    return ctx.meta.get(_CELL_KEY) is not None or source not in (
        None,
        click.core.ParameterSource.DEFAULT,
    )


def _keep_cell(ctx: click.Context, param: click.Parameter, value: str | None) -> None:
    if value is not None:
        earlier = ctx.meta.get(_CELL_KEY)
        if earlier is not None and Path(earlier) != Path(value):
            raise UsageError(f"--cell given twice: {earlier} and {value}; give one")
        ctx.meta[_CELL_KEY] = value


def cell_option() -> click.Option:
    """``--cell DIR`` for a subcommand: the same as ``cellctl --cell DIR`` before it."""
    return click.Option(
        ["--cell"],
        type=click.Path(file_okay=False),
        default=None,
        expose_value=False,
        callback=_keep_cell,
        help="Cell directory (the same as `cellctl --cell DIR` before the command).",
    )


def accept_cell_anywhere(group: click.Group) -> None:
    """Give every command under ``group`` that takes the cell its own ``--cell``, so that
    ``cellctl orders --cell mycell`` means ``cellctl --cell mycell orders``."""

    def walk(command: click.Command, top: str) -> None:
        if top in NO_CELL_COMMANDS:
            return
        if top == "emulate" and command.name not in ("emulate", "cell"):
            return  # one emulated machine takes no cell; `emulate cell` writes one
        if not any(p.name == "cell" for p in command.params):
            command.params.append(cell_option())
        if isinstance(command, click.Group):
            for sub in command.commands.values():
                walk(sub, top)

    for name, command in group.commands.items():
        walk(command, name)


class MachineGroup(click.Group):
    """A group that takes an optional machine NAME before its command: ``robot r1 status``."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        rest = list(args)
        # Options come first; the first bare word that is not a command is the machine NAME.
        i = 0
        while i < len(rest):
            word = rest[i]
            if word.startswith("-"):
                opt = self._option_for(ctx, word)
                i += 1 if opt is None or opt.is_flag or "=" in word else 2
                continue
            if word not in self.commands:
                ctx.meta["machine_name"] = word
                del rest[i]
            break
        return super().parse_args(ctx, rest)

    def _option_for(self, ctx: click.Context, word: str) -> click.Option | None:
        name = word.split("=", 1)[0]
        for param in self.get_params(ctx):
            if isinstance(param, click.Option) and name in param.opts + param.secondary_opts:
                return param
        return None


async def until_stopped() -> None:
    """Wait until Ctrl-C or SIGTERM (what every ``cellctl emulate`` command serves until)."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


def machine_ref(ctx: click.Context, family: str) -> tuple[Path, MachineRef]:
    """The cell directory and the machine a ``robot``/``mill`` command means (NAME or --link)."""
    params = ctx.find_object(dict) or {}
    directory = cell_dir(ctx)
    ref = resolve_machine(
        directory,
        family,
        name=ctx.meta.get("machine_name"),
        link=params.get("link"),
        line=params.get("line"),
    )
    return directory, ref


def fault_help(faults: dict[str, str]) -> str:
    """The fault switches as a help paragraph, one a line (click keeps ``\\b`` blocks)."""
    return "\b\nFaults (--fault NAME[=ARG]):\n" + "\n".join(
        f"  {name}: {text}" for name, text in faults.items()
    )


#: The width a group's help is laid out for: a summary must read whole there.
HELP_WIDTH = 80


def clause_summary(text: str, limit: int) -> str:
    """The first line of ``text`` cut back to whole clauses within ``limit`` characters.

    Click cuts a long first line mid-sentence with "..."; this keeps what reads whole: up to
    the last ": ", "; ", ", " or " (" that fits ("Emergency stop: stop the robot, halt the
    mills"), else the words that fit.
    """
    line = " ".join(text.strip().split("\n\n", 1)[0].split())
    if len(line) <= limit:
        return line.rstrip(".")
    cuts, depth = [], 0  # clause ends outside any parenthesis
    for i, ch in enumerate(line[: limit + 1]):
        if ch == "(":
            if depth == 0 and i > 0:
                cuts.append(i)  # before a parenthesis: what precedes reads whole
            depth += 1
        elif ch == ")":
            depth = max(0, depth - 1)
        elif depth == 0 and ch in ":;," and line[i + 1 : i + 2] == " ":
            cuts.append(i)
    if cuts:
        return line[: cuts[-1]].rstrip(" ,;:")
    return line[: line.rfind(" ", 0, limit + 1)] if " " in line[:limit] else line[:limit]


def summarize_commands(group: click.Group) -> None:
    """Give every command under ``group`` a summary that reads whole in its group's help at
    :data:`HELP_WIDTH` columns (a command that sets its own ``short_help`` keeps it)."""
    commands = [c for c in group.commands.values() if not c.hidden]
    if not commands:
        return
    # Click's own layout: the widest name and 6 columns of indent and gap.
    limit = HELP_WIDTH - 6 - max(len(c.name or "") for c in commands)
    for command in commands:
        if command.short_help is None and command.help:
            command.short_help = clause_summary(command.help, limit)
        if isinstance(command, click.Group):
            summarize_commands(command)
