"""``cellctl emulate``: serve an emulated machine until stopped."""

from __future__ import annotations

import click

from cellctl.emulators.serve import EmulatedDevice, serve
from cellctl.link import LineSettings
from cellctl.ui.common import console, until_stopped
from cellctl.ui.plc_cli import emulate_plc


@click.group()
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
            default=1.0,
            show_default=True,
            help="Machine times divided by this (10 = ten times faster).",
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
    device: EmulatedDevice, listen: str, line: str, pacing: bool, what: str
) -> None:
    """Serve ``device``, print where, and run until Ctrl-C or SIGTERM."""
    settings = LineSettings.parse(line)
    server = await serve(device, listen, settings, pacing=pacing)
    paced = "on" if pacing else "off"
    console.print(f"{what} listening on {server.url}  ({settings}, pacing {paced})")
    console.print(f"  drive it with: --link {server.url}")
    try:
        await until_stopped()
    finally:
        await server.close()
        console.print(f"{what} stopped")


emulate.add_command(emulate_plc)
