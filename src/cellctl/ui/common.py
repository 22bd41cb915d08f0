"""Pieces every command shares: running a coroutine, one-line errors, exit codes."""

from __future__ import annotations

import asyncio
import logging
import signal
import sys
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any, NoReturn, TypeVar

import click
from rich.console import Console
from rich.markup import escape

from cellctl.errors import CellctlError, exit_code
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


def cell_dir(ctx: click.Context) -> Path:
    """The cell directory chosen with ``--cell`` (or its default)."""
    root = ctx.find_root()
    return Path(root.params.get("cell") or "cell")


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
