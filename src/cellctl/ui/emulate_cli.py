"""``cellctl emulate``: serve an emulated machine until stopped."""

from __future__ import annotations

import click

from cellctl.emulators.serve import EmulatedDevice, parse_fault, serve
from cellctl.errors import UsageError
from cellctl.link import ROBOT_LINE, LineSettings
from cellctl.ui.common import console, fault_help, run, until_stopped
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


def _robot_command() -> click.Command:
    from cellctl.emulators.robot import FAULTS, Ibm7545Emulator

    def callback(
        listen: str, time_scale: float, no_pacing: bool, line: str, fault: tuple[str, ...]
    ) -> None:
        async def main() -> None:
            device = Ibm7545Emulator(time_scale=time_scale)
            for text in fault:
                name, arg = parse_fault(text)
                if name not in FAULTS:
                    raise UsageError(f"unknown fault {name!r}; known: {', '.join(FAULTS)}")
                device.set_fault(name, arg)
            await serve_until_stopped(device, listen, line, not no_pacing, "IBM 7545 emulator")

        run(main)

    return click.Command(
        "robot",
        callback=callback,
        params=listen_options(ROBOT_LINE, FAULTS),
        help="Emulate an IBM 7545/7547 robot controller.\n\n" + fault_help(FAULTS),
    )


emulate.add_command(_robot_command())
emulate.add_command(emulate_plc)
