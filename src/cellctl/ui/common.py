"""Pieces every command shares: running a coroutine, one-line errors, exit codes."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import importlib
import json
import logging
import signal
import sys
import threading
from collections.abc import (
    Awaitable,
    Callable,
    Coroutine,
    Iterable,
    Iterator,
    Mapping,
    Sequence,
)
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn, TypeVar

import click
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from cellctl.clock import current_clock
from cellctl.errors import CellctlError, UsageError, exit_code

# Re-exported: the kinds' command lines build their family groups from here.
from cellctl.ui.machine_group import MachineGroup as MachineGroup

if TYPE_CHECKING:
    from cellctl.service.machines import MachineRef

# The kind registry (every kind's declaration, and pydantic with it) is imported by what uses
# it: a command that only asks a running controller (`cellctl alarm list`) needs none of it.

T = TypeVar("T")
FC = TypeVar("FC", bound=Callable[..., Any])

log = logging.getLogger(__name__)


class _Console(Console):
    """A console that wraps lines at the terminal's width on a terminal, and never in a pipe:
    ``cellctl cell check | grep`` sees each message on one line, whatever its length."""

    @property
    def soft_wrap(self) -> bool:
        return self._soft_wrap or not self.is_terminal

    @soft_wrap.setter
    def soft_wrap(self, value: bool) -> None:
        self._soft_wrap = value


console = _Console(highlight=False, emoji=False)  # "file:100:" is no emoji code
err_console = _Console(stderr=True, highlight=False, emoji=False)


def run(coro_fn: Callable[[], Coroutine[Any, Any, T]]) -> T:
    """Run a command's coroutine; a CellctlError becomes one line on stderr and an exit code,
    Ctrl-C or SIGTERM "interrupted" and 130 (the coroutine cancelled first, as
    ``asyncio.run`` does on Ctrl-C: its ``finally`` blocks run)."""
    # The PLC driver turns pymodbus failures into typed errors; pymodbus's own error log
    # (with frame dumps) would only repeat them on the operator's screen.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        with sigterm_interrupts():
            return asyncio.run(coro_fn())
    except CellctlError as e:
        fail(e)
    except KeyboardInterrupt:
        interrupted()


def interrupted() -> NoReturn:
    """End a command stopped by Ctrl-C or SIGTERM as README says: "interrupted" on stderr,
    exit status 130 (128 + SIGINT: what a shell shows for a command Ctrl-C ended)."""
    err_console.print("interrupted")
    sys.exit(128 + signal.SIGINT)


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM stops what runs in the block as Ctrl-C does (a KeyboardInterrupt, or the
    handler that takes Ctrl-C then: asyncio's cancels the command's coroutine), not the
    process at once: what the command started (worker processes, a machine's session) is
    ended, and the command ends with "interrupted" and 130.

    Only from the main thread, and only over the default action: a SIGTERM ignored or handled
    by whoever started us, or by an enclosing block, stays theirs. A handler set inside the
    block (:func:`stop_signals`) takes it meanwhile."""
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL
    ):
        yield
        return
    signal.signal(signal.SIGTERM, _sigterm_as_ctrl_c)
    try:
        yield
    finally:
        if signal.getsignal(signal.SIGTERM) is _sigterm_as_ctrl_c:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _sigterm_as_ctrl_c(signum: int, frame: object) -> None:
    """:func:`sigterm_interrupts`'s handler: Ctrl-C sent to this process, to be taken as Ctrl-C
    is taken now; a KeyboardInterrupt at once where Ctrl-C would be lost (ignored, blocked)."""
    sigint = signal.getsignal(signal.SIGINT)
    blocked = signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])
    if sigint in (signal.SIG_IGN, signal.SIG_DFL, None) or blocked:
        raise KeyboardInterrupt
    signal.raise_signal(signal.SIGINT)


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
    wide = Console(file=console.file, width=100_000, highlight=False, no_color=True, emoji=False)
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


@dataclass(frozen=True)
class Lazy:
    """A command imported when it is used: ``"module:attribute"`` (a command, or a function
    that makes one), and its summary for the group's help (so that ``cellctl --help`` imports
    no command's module)."""

    target: str
    summary: str

    def load(self) -> click.Command:
        module, _, attribute = self.target.partition(":")
        command = getattr(importlib.import_module(module), attribute)
        if not isinstance(command, click.Command) and callable(command):
            command = command()
        if not isinstance(command, click.Command):
            raise TypeError(f"{self.target} is not a click command")
        return command


class LazyGroup(CellctlGroup):
    """A group whose commands are imported only when one is used: ``cellctl orders`` imports
    the orders commands, not the controller, the API server or the broker client.

    ``lazy`` names each command's module and summary; ``more(name)`` gives further commands
    (the installed kinds'): those that may be ``name``, a name the group does not know, or all
    of them (``None``) when the group needs them all (its help); ``prepare(name, command)``
    finishes a command as it is loaded (``--cell`` anywhere)."""

    def __init__(
        self,
        *args: Any,
        lazy: Mapping[str, Lazy] | None = None,
        more: Callable[[str | None], Iterable[click.Command]] | None = None,
        prepare: Callable[[str, click.Command], None] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        self.lazy = dict(lazy or {})
        self._more = more
        self._all_added = more is None
        self._prepare = prepare

    def _add_more(self, name: str | None = None) -> None:
        if self._all_added or self._more is None:
            return
        self._all_added = name is None
        for command in self._more(name):
            if self.commands.get(command.name or "") is command:
                continue  # added already, when its name was asked for
            if command.name in self.commands or command.name in self.lazy:
                log.warning("command %s given twice: the first one is used", command.name)
                continue
            self._added(command.name or "", command)

    def _added(self, name: str, command: click.Command) -> None:
        self.add_command(command, name)
        if command.short_help is None and command.help:
            command.short_help = clause_summary(command.help, self.summary_limit())
        if isinstance(command, click.Group) and not isinstance(command, LazyGroup):
            summarize_commands(command)
        if self._prepare is not None:
            self._prepare(name, command)

    def summary_limit(self) -> int:
        """How long a command's summary may be in this group's help (Click's layout: the
        widest name and 6 columns of indent and gap, in :data:`HELP_WIDTH`)."""
        return HELP_WIDTH - 6 - max(len(n) for n in (*self.commands, *self.lazy))

    def list_commands(self, ctx: click.Context) -> list[str]:
        self._add_more()
        return sorted({*self.commands, *self.lazy})

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in self.commands and cmd_name in self.lazy:
            command = self.lazy[cmd_name].load()
            if command.short_help is None:
                command.short_help = self.lazy[cmd_name].summary
            self._added(cmd_name, command)
        if cmd_name not in self.commands:
            self._add_more(cmd_name)
        return self.commands.get(cmd_name)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """Click's list of commands, with a command not yet imported shown by its summary."""
        rows = []
        for name in self.list_commands(ctx):
            command = self.commands.get(name)
            if command is None:
                rows.append((name, self.lazy[name].summary))
            elif not command.hidden:
                rows.append((name, command.get_short_help_str(self.summary_limit())))
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


def subcommands(group: click.Group) -> dict[str, click.Command]:
    """Every command of ``group`` by name, imported as a user's ``--help`` reaches it (a lazy
    group's ``commands`` holds only those loaded so far)."""
    ctx = click.Context(group, info_name=group.name)
    found = {name: group.get_command(ctx, name) for name in group.list_commands(ctx)}
    return {name: command for name, command in found.items() if command is not None}


#: The groups kinds contribute commands to besides a group another kind contributed.
KIND_GROUPS = ("", "emulate")


def kind_commands(group: str, name: str | None = None) -> list[click.Command]:
    """The commands the installed kinds contribute to ``group`` (``""`` the top level,
    ``"emulate"``): all of them, or those that may be called ``name``. A kind that lists its
    commands (``MachineKind.command_names``) has its CLI imported only for them: ``cellctl dnc``
    imports no robot's. A kind's command for a group another kind contributed (``cellctl
    robot unlock``) is added to that group."""
    from cellctl.kinds import registry

    contributed = [
        (kind.name, to, command)
        for kind in registry.kinds()
        if name is None or _may_give(kind.command_names, group, name)
        for to, command in _contributed(kind.name)
    ]
    mine = [command for _, to, command in contributed if to == group]
    if group == "":
        groups = {command.name: command for command in mine}
        for kind_name, to, command in contributed:
            if to in KIND_GROUPS:
                continue
            target = groups.get(to)
            if not isinstance(target, click.Group):
                registry.log.warning("machine kind %s: no command group %r", kind_name, to)
                continue
            target.add_command(command)
        from cellctl.ui.kind_check import check_kinds

        for command in groups.values():
            if isinstance(command, MachineGroup):
                check_kinds(command)
    return mine


def _may_give(names: Sequence[tuple[str, str]] | None, group: str, name: str) -> bool:
    """Whether a kind that lists ``names`` ((group, name); None: it does not say) may give
    command ``name`` of ``group``, or, at the top level, a command added to group ``name``."""
    if names is None:
        return True
    return (group, name) in names or (group == "" and any(to == name for to, _ in names))


@functools.cache
def _contributed(kind_name: str) -> tuple[tuple[str, click.Command], ...]:
    """What kind ``kind_name``'s ``commands`` gives, made once per process; a plug-in's CLI
    that fails to load is skipped and named."""
    from cellctl.kinds import registry

    kind = registry.kind(kind_name)
    try:
        return tuple(kind.commands()) if kind.commands is not None else ()
    except Exception as e:  # a plug-in's CLI that fails to load: skipped, by name
        registry.log.warning("machine kind %s: its commands skipped: %s", kind.name, e)
        return ()


#: Where a command's own ``--cell`` (after the command's name) keeps its value.
_CELL_KEY = "cellctl.cell"

#: Top-level commands that do not take a cell (the factory has its own ``--dir``).
NO_CELL_COMMANDS = frozenset({"examples", "factory", "kinds"})


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


def accept_cell(command: click.Command, top: str) -> None:
    """Give ``command`` (top-level command ``top`` or one under it) and every command under
    it that takes the cell its own ``--cell``, so that ``cellctl orders --cell mycell`` means
    ``cellctl --cell mycell orders``."""
    if top in NO_CELL_COMMANDS:
        return
    if top == "emulate" and command.name not in ("emulate", "cell"):
        return  # one emulated machine takes no cell; `emulate cell` writes one
    if not any(p.name == "cell" for p in command.params):
        command.params.append(cell_option())
    if isinstance(command, click.Group):
        for sub in command.commands.values():
            accept_cell(sub, top)


#: The signals that stop a command that serves or follows until told: Ctrl-C and SIGTERM.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: Seconds a ``--follow`` step cut short by Ctrl-C may take to wind down.
STOP_GRACE_S = 5.0


def _restorable(handler: Any) -> bool:
    """Whether a handler found before :func:`stop_signals` is put back after it. Not one set
    outside Python (None), and not asyncio.Runner's own Ctrl-C handler: that one is bound to
    the run that set it, and a block may end in another run (a test fixture's teardown);
    the loop then leaves Python's default, as it does by itself."""
    # asyncio.Runner sets a partial of one of its own methods: known by its owner's type.
    owner = getattr(getattr(handler, "func", None), "__self__", None)
    return handler is not None and not isinstance(owner, asyncio.Runner)


@contextlib.contextmanager
def stop_signals(stop: asyncio.Event | Callable[[], object]) -> Iterator[None]:
    """Set ``stop`` (or call it) on Ctrl-C or SIGTERM while in the block; then put back what
    was there.

    The loop's own handler takes the signal even when this process started with it ignored
    or blocked (a state a parent's exec passes on); on leaving, the handlers and the mask are
    what they were, so a command run in a longer-lived process (a test) leaves them as found
    (the loop alone would leave Python's default handler, not an ignored SIGINT).
    """
    loop = asyncio.get_running_loop()
    callback = stop.set if isinstance(stop, asyncio.Event) else stop
    before = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    mask = signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, callback)
    try:
        yield
    finally:
        for sig, handler in before.items():
            loop.remove_signal_handler(sig)
            if _restorable(handler):
                signal.signal(sig, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def stdin_lines() -> asyncio.Queue[str]:
    """stdin's lines as they are typed, on a queue of the running loop ("" at its end): a
    hand panel's input (an emulator's ``--panel``, ``emulate cell --panel``). Read in a
    daemon thread: a readline that blocks there never holds the process at exit (Ctrl-C),
    as one in the loop's executor would until Enter."""
    loop = asyncio.get_running_loop()
    lines: asyncio.Queue[str] = asyncio.Queue()

    def read() -> None:
        try:
            for text in iter(sys.stdin.readline, ""):
                loop.call_soon_threadsafe(lines.put_nowait, text)
            loop.call_soon_threadsafe(lines.put_nowait, "")
        except RuntimeError:
            return  # the loop has closed: the command ended

    threading.Thread(target=read, daemon=True).start()
    return lines


async def until_stopped() -> None:
    """Wait until Ctrl-C or SIGTERM (what every ``cellctl emulate`` command serves until)."""
    stop = asyncio.Event()
    with stop_signals(stop):
        await stop.wait()


async def follow_until_stopped(step: Callable[[], Awaitable[None]], period: float) -> NoReturn:
    """Run ``step()`` every ``period`` s until Ctrl-C or SIGTERM, then raise KeyboardInterrupt
    (:func:`run` prints "interrupted" and exits 130): the loop of every ``--follow``.

    The stop is an event the signal sets, looked at between steps and raced against each,
    never only a cancel of the command's task (which a wait inside a step could swallow).
    A step's error ends the loop with that error.
    """
    stop = asyncio.Event()
    with stop_signals(stop):
        while not stop.is_set():
            await _unless_stopped(stop, step())
            await _unless_stopped(stop, current_clock().sleep(period))
    raise KeyboardInterrupt


async def _unless_stopped(stop: asyncio.Event, work: Awaitable[None]) -> None:
    """``work`` to its end, or cut short (cancelled, given :data:`STOP_GRACE_S`) once ``stop``
    is set; its error, if it ended with one."""
    task = asyncio.ensure_future(work)
    stopped = asyncio.ensure_future(stop.wait())
    try:
        await asyncio.wait({task, stopped}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        stopped.cancel()
        if not task.done():
            task.cancel()
            await asyncio.wait({task}, timeout=STOP_GRACE_S)
    if task.done() and not task.cancelled():
        task.result()


def machine_ref(
    ctx: click.Context, family: str, function: str | None = None
) -> tuple[Path, MachineRef]:
    """The cell directory and the machine a ``robot``/``mill`` command (``function``) means:
    NAME or ``--link``, and ``--kind``."""
    from cellctl.service.machines import resolve_machine

    params = ctx.find_object(dict) or {}
    directory = cell_dir(ctx)
    ref = resolve_machine(
        directory,
        family,
        name=ctx.meta.get("machine_name"),
        link=params.get("link"),
        line=params.get("line"),
        kind=params.get("kind"),
        function=function,
    )
    return directory, ref


def kind_option(family: str) -> Callable[[FC], FC]:
    """``--kind KIND`` for the ``family`` command group (``cellctl robot --kind ...``)."""
    return click.option(
        "--kind",
        metavar="KIND",
        callback=_not_broken,
        help=f"The {family}'s kind (`cellctl kinds`): at --link, what it is driven as (default: "
        f"the first {family} kind that has the command); with a NAME, checked against cell.toml.",
    )


def _not_broken(ctx: click.Context, param: click.Parameter, kind: str | None) -> str | None:
    """Refuse ``--kind`` of a kind installed but broken, saying why (BrokenKind); an unknown
    one is refused naming the family's kinds, as the machine is resolved."""
    if kind is not None:
        from cellctl.kinds import registry

        with contextlib.suppress(UsageError):
            registry.kind(kind)
    return kind


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
