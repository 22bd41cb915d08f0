"""``cellctl emulate``: serve an emulated machine until stopped."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import click

from cellctl.emulators.serve import (
    MACHINE_TIME_SCALE,
    TIME_SCALE_HELP,
    EmulatedDevice,
    Server,
    serve,
)
from cellctl.link import LineSettings
from cellctl.ui.common import Lazy, LazyGroup, accept_cell, console, kind_commands, until_stopped

if TYPE_CHECKING:
    from cellctl.emulators.fleet import Fleet


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
    more=lambda: kind_commands()["emulate"],
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


async def serve_until_stopped(
    device: EmulatedDevice,
    listen: str,
    line: str,
    pacing: bool,
    what: str,
    hint: str = "drive it with: --link {url}",
) -> None:
    """Serve ``device``, print where and ``hint`` (how to drive it, with its ``{url}``), and
    run until Ctrl-C or SIGTERM."""
    settings = LineSettings.parse(line)
    server = await serve(device, listen, settings, pacing=pacing)
    paced = "on" if pacing else "off"
    console.print(f"{what} listening on {server.url}  ({settings}, pacing {paced})")
    console.print("  " + hint.format(url=server.url), soft_wrap=True)
    try:
        await until_stopped()
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
) -> None:
    """Serve ``count`` machines (``make(i)`` each) over ``workers`` processes, print where
    each listens (``hint`` with its ``{url}``), and run until Ctrl-C or SIGTERM."""
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
        console.print(
            f"{count} x {what} in {workers} process{'es' if workers > 1 else ''}  "
            f"({settings}, pacing {paced})"
        )
        for i, url in enumerate(urls, 1):
            console.print(f"  {i}: " + hint.format(url=url), soft_wrap=True)
        await until_stopped()
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
