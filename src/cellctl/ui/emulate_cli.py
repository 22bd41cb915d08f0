"""``cellctl emulate``: serve an emulated machine until stopped."""

from __future__ import annotations

import asyncio
import math
import os
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import click

from cellctl.cell.owner import controller_holder
from cellctl.emulators.serve import (
    MACHINE_TIME_SCALE,
    TIME_SCALE_HELP,
    EmulatedDevice,
    Server,
    pty_link_path,
    pty_lock_path,
    serve,
)
from cellctl.emulators.switches import parse_fault, said_switched_on
from cellctl.errors import MachineInUse
from cellctl.link import LineSettings
from cellctl.link.lock import Holder, holder
from cellctl.ui.common import (
    Lazy,
    LazyGroup,
    accept_cell,
    console,
    kind_commands,
    stop_signals,
)

if TYPE_CHECKING:
    from cellctl.emulators.fleet import Fleet


class TimeScale(click.FloatRange):
    """A ``--time-scale``: a number in the range of the cell file's ``[cell] time_scale``
    (:class:`cellctl.cell.configschema.CellTable`, the one table of it), so the command
    refuses it, naming the option and the range, before it writes a cell that would refuse
    it. Unlike a plain FloatRange, ``nan`` is refused too.

    The bounds are read from the schema when first used (a conversion, ``--help``): a
    command that only imports this module loads no schema."""

    name = "float"

    def __init__(self) -> None:  # the range's attributes come from __getattr__
        pass

    def __getattr__(self, name: str) -> Any:
        if name not in ("min", "max", "min_open", "max_open", "clamp"):
            raise AttributeError(name)
        from cellctl.cell.configschema import CellTable

        limits = CellTable.model_fields["time_scale"].metadata  # [Gt(0), Le(...), ...]
        low = next(m.gt for m in limits if hasattr(m, "gt"))
        high = next(m.le for m in limits if hasattr(m, "le"))
        click.FloatRange.__init__(self, min=low, min_open=True, max=high)
        return getattr(self, name)

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> float:
        scale = super().convert(value, param, ctx)
        if math.isnan(scale):  # no comparison refuses it
            self.fail(f"{value} is not in the range {self._describe_range()}.", param, ctx)
        return scale


#: The type of every cell-wide ``--time-scale`` (``demo``, ``emulate cell``, ``emulate factory``).
TIME_SCALE = TimeScale()


@click.group(
    cls=LazyGroup,
    lazy={
        "cell": Lazy(
            "cellctl.ui.cell_cli:emulate_cell_command", "Start the robot, both mills and the PLC"
        ),
        "factory": Lazy(
            "cellctl.ui.factory_cli:emulate_factory",
            "Start a private Mosquitto and COUNT emulated cells",
        ),
        "plc": Lazy("cellctl.ui.plc_cli:emulate_plc", "Emulate the cell PLC (Modbus/TCP)"),
    },
    # The machines the installed kinds emulate (``emulate robot``, ``emulate mill`` ...).
    more=lambda name: kind_commands("emulate", name),
    prepare=lambda name, command: accept_cell(command, "emulate"),
)
def emulate() -> None:
    """Emulated machines that speak the real bytes: serve one, point a driver at it."""


def listen_options(
    default_line: LineSettings, faults: dict[str, str] | None = None
) -> list[click.Parameter]:
    """The options every ``emulate`` command takes."""
    names = ", ".join(faults) if faults else "see above"
    return [
        click.Option(
            ["--listen"],
            default="pty",
            show_default=True,
            help="pty, pty:PATH (symlink), socket://HOST:PORT or rfc2217://HOST:PORT.",
        ),
        click.Option(
            ["--time-scale"],
            type=float,
            default=MACHINE_TIME_SCALE,
            show_default=True,
            help="Machine times divided by this (10 = ten times faster). " + TIME_SCALE_HELP,
        ),
        click.Option(["--no-pacing"], is_flag=True, help="Move bytes as fast as they come."),
        click.Option(
            ["--line"], default=str(default_line), show_default=True, help="Line settings."
        ),
        click.Option(
            ["--fault"], multiple=True, metavar="NAME[=ARG]", help=f"Fault switch: {names}."
        ),
    ]


class Switchable(Protocol):
    """An emulator with fault switches: each kind's, the PLC's."""

    def set_fault(self, name: str, arg: str | None = None) -> None: ...


def switch_faults(device: Switchable, faults: Mapping[str, str], texts: Iterable[str]) -> list[str]:
    """Switch each ``--fault NAME[=ARG]`` of ``texts`` on at ``device`` (``faults`` its table;
    its ``set_fault`` refuses a switch it does not have, or a bad argument, in words) and
    return what each switched on says, as :func:`say_faults` prints it::

        said = switch_faults(device, FAULTS, ("drop", "noise=3e-4"))
        # ["drop on (5 lines, its default)", "noise=3e-4 on"]"""
    said = []
    for text in texts:
        name, arg = parse_fault(text)
        device.set_fault(name, arg)
        said.append(said_switched_on(name, arg, faults))
    return said


def say_faults(said: Sequence[str]) -> None:
    """Print a line a fault switched on (from :func:`switch_faults`), after where an emulator
    listens, as ``emulate cell`` says them: ``  fault drop on (5 lines, its default)``."""
    for line in said:
        # Plain text: a switch's argument is the user's, not markup.
        console.print(f"  fault {line}", markup=False, highlight=False, soft_wrap=True)


#: What a command is told when a running one holds its directory; ``{what}`` is the
#: directory, ``{holder}`` the holder, ``{held}`` what it holds there.
DIRECTORY_IN_USE = "{what} is in use by {holder}, which {held}: stop it or choose another directory"


def _directories(top: Path, depth: int) -> Iterator[Path]:
    """``top`` and the directories under it down to ``depth`` levels, links not followed."""
    yield top
    if depth == 0:
        return
    try:
        entries = sorted(os.scandir(top), key=lambda e: e.name)
    except OSError:
        return  # missing, or not ours to read: nothing of a run of ours below
    for entry in entries:
        if entry.is_dir(follow_symlinks=False):
            yield from _directories(Path(entry.path), depth - 1)


def _pty_held(directory: Path) -> tuple[Holder | None, str]:
    robot = pty_link_path(str(directory / "robot.pty"))
    return holder(pty_lock_path(robot)), f"serves pty:{robot}"


def _factory_held(directory: Path) -> tuple[Holder | None, str]:
    # The factory's config (its models, the mailbox's records) is not imported by every
    # emulator's start: only where a factory's directory is looked at.
    from cellctl.factory.config import factory_lock_path

    return holder(factory_lock_path(directory)), f"runs the factory in {directory}"


def _controller_held(directory: Path) -> tuple[Holder | None, str]:
    return controller_holder(directory), f"runs the cell in {directory}"


def refuse_if_running_in(directory: Path | str) -> None:
    """MachineInUse, naming the holder (pid and command), if a run holds ``directory``, a
    directory in it, or one in those: an emulated cell's robot pty (``cellctl emulate cell``
    or ``factory``, ``cellctl demo``), a factory's controller or a cell's.

    Takes nothing and writes nothing: a command that replaces or writes files there (a
    demo's ``--out``, an emulated factory's directory) calls it first, so a second run is
    refused before the first one's files are touched."""
    directories = list(_directories(Path(directory), 2))
    # An emulator's pty first: its holder is the process that started the rest (a demo, an
    # emulated factory), where a cell's controller may be a child of it.
    for held in (_pty_held, _factory_held, _controller_held):
        for d in directories:
            found, what = held(d)
            if found is not None:
                raise MachineInUse(DIRECTORY_IN_USE.format(what=directory, holder=found, held=what))


async def serve_until_stopped(
    device: EmulatedDevice,
    listen: str,
    line: str,
    pacing: bool,
    what: str,
    hint: str = "drive it with: --link {url}",
    said: Sequence[str] = (),
) -> None:
    """Serve ``device``, print where and ``hint`` (how to drive it, with its ``{url}``; plain
    text, lines after its first indented by the caller), then each fault switched on
    (``said``, from :func:`switch_faults`), and run until Ctrl-C or SIGTERM, then say "WHAT
    stopped".

    Ctrl-C and SIGTERM are taken before anything is printed: whoever reads the hint and
    stops it at once gets the same clean stop as later."""
    settings = LineSettings.parse(line)
    stop = asyncio.Event()
    with stop_signals(stop):
        server = await serve(device, listen, settings, pacing=pacing)
        try:
            paced = "on" if pacing else "off"
            console.print(f"{what} listening on {server.url}  ({settings}, pacing {paced})")
            # The hint is plain text: a TOML table's [name] is not markup.
            console.print("  " + hint.format(url=server.url), soft_wrap=True, markup=False)
            say_faults(said)
            await stop.wait()
        finally:
            await server.close()
            console.print(f"{what} stopped")


async def serve_fleet_until_stopped(
    make: Callable[[int], EmulatedDevice],
    listen: str,
    line: str,
    pacing: bool,
    what: str,
    count: int,
    workers: int,
    hint: str = "drive it with: --link {url}",
    said: Sequence[str] = (),
) -> None:
    """Serve ``count`` machines (``make(i)`` each) over ``workers`` processes, print where
    each listens (``hint`` with its ``{url}``), then each fault switched on (``said``: the
    same on every machine), and run until Ctrl-C or SIGTERM."""
    from cellctl.emulators.fleet import Fleet, check_fleet, serve_many

    settings = LineSettings.parse(line)
    check_fleet(listen, count, workers)
    servers: list[Server] = []
    fleet: Fleet | None = None
    try:
        if workers == 1:
            servers = await serve_many(
                make, listen, settings, pacing=pacing, indices=range(count), count=count
            )
            urls = [s.url for s in servers]
        else:
            fleet = Fleet.start(make, listen, settings, count=count, workers=workers, pacing=pacing)
            urls = fleet.urls
        paced = "on" if pacing else "off"
        # Ctrl-C and SIGTERM taken before anything is printed, as serve_until_stopped does
        # (whoever stops it once it has said all gets a clean stop), but after the workers
        # are forked: they must not inherit this loop's handlers.
        stop = asyncio.Event()
        with stop_signals(stop):
            console.print(
                f"{count} x {what} in {workers} process{'es' if workers > 1 else ''}  "
                f"({settings}, pacing {paced})"
            )
            for i, url in enumerate(urls, 1):
                console.print(f"  {i}: " + hint.format(url=url), soft_wrap=True, markup=False)
            say_faults(said)
            await stop.wait()
    finally:
        for s in servers:
            await s.close()
        if fleet is not None:
            fleet.close()
        console.print(f"{what} stopped")


def fleet_options() -> list[click.Parameter]:
    """``--count`` and ``--workers``: many machines of one kind, over several processes."""
    return [
        click.Option(
            ["--count"],
            type=int,
            default=1,
            show_default=True,
            help="Machines to emulate, each with its own state and link (pty: one each; "
            "socket://HOST:0 a free port each; socket://HOST:PORT ports PORT, PORT+1, ...).",
        ),
        click.Option(
            ["--workers"],
            type=int,
            default=1,
            show_default=True,
            help="Processes to spread the machines over (one core paces a few thousand "
            "lines at most).",
        ),
    ]
