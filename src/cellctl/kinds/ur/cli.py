"""``cellctl emulate ur``: a UR controller's three interfaces on this machine."""

from __future__ import annotations

import asyncio

import click

from cellctl.emulators.serve import MACHINE_TIME_SCALE, TIME_SCALE_HELP
from cellctl.errors import UsageError
from cellctl.files import read_text, reason
from cellctl.kinds.ur.emulator import FAULTS, UrEmulator
from cellctl.kinds.ur.kind import ROBOT_FUNCTIONS
from cellctl.kinds.ur.motion import ARMS
from cellctl.kinds.ur.options import UrOptions, drive_command
from cellctl.ui.common import console, fault_help, run


def _programs(items: tuple[str, ...]) -> dict[str, str]:
    out = {}
    for item in items:
        path, sep, file = item.partition("=")
        if not sep or not path.endswith(".urp"):
            raise UsageError(f"--program takes ROBOT_PATH.urp=SCRIPT_FILE, not {item!r}")
        try:
            out[path] = read_text(file)
        except (OSError, UnicodeDecodeError) as e:
            raise UsageError(f"{file}: cannot read it: {reason(e)}") from None
    return out


@click.command("ur", help="Emulate a Universal Robots controller: Dashboard Server, "
               "secondary interface and RTDE.\n\n" + fault_help(FAULTS))  # fmt: skip
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to listen on.")
@click.option(
    "--dashboard-port", default=29999, show_default=True, help="Dashboard Server port (0: free)."
)
@click.option(
    "--secondary-port", default=30002, show_default=True, help="Secondary interface port (0: free)."
)
@click.option("--rtde-port", default=30004, show_default=True, help="RTDE port (0: free).")
@click.option(
    "--model", type=click.Choice(sorted(ARMS)), default="UR5e", show_default=True, help="The arm."
)
@click.option(
    "--time-scale",
    type=float,
    default=MACHINE_TIME_SCALE,
    show_default=True,
    help="Machine times divided by this (10 = ten times faster). " + TIME_SCALE_HELP,
)
@click.option("--program", "programs", multiple=True,
              help="A .urp on the robot as a URScript file: /programs/a.urp=a.script.")  # fmt: skip
@click.option("--fault", multiple=True, help="Switch a fault on at start: NAME.")
def emulate_ur(
    host: str,
    dashboard_port: int,
    secondary_port: int,
    rtde_port: int,
    model: str,
    time_scale: float,
    programs: tuple[str, ...],
    fault: tuple[str, ...],
) -> None:
    async def main() -> None:
        from cellctl.ui.common import stop_signals

        # Here, not at the top: the UR's `cellctl robot` commands serve nothing.
        from cellctl.ui.emulate_cli import say_faults, switch_faults

        emulator = UrEmulator(time_scale=time_scale, model=model, programs=_programs(programs))
        said = switch_faults(emulator, FAULTS, fault)
        # Ctrl-C and SIGTERM taken before anything is printed: whoever reads the hint and
        # stops it at once gets the same clean stop as later.
        stop = asyncio.Event()
        with stop_signals(stop):
            ports = await emulator.start(
                host, dashboard=dashboard_port, secondary=secondary_port, rtde_port=rtde_port
            )
            try:
                _say_where(emulator, model, time_scale, host, ports)
                say_faults(said)
                await stop.wait()
            finally:
                await emulator.close()
                console.print("UR emulator stopped")  # as every emulator says it

    run(main)


def _say_where(
    emulator: UrEmulator, model: str, time_scale: float, host: str, ports: dict[str, int]
) -> None:
    """Where ``cellctl emulate ur`` listens, and how to drive it."""
    console.print(f"UR emulator ({model}, time scale {time_scale:g}) on {host}")
    console.print(
        f"  ports: dashboard {ports['dashboard']}, secondary {ports['secondary']}, "
        f"RTDE {ports['rtde']}"
    )
    # The driver finds RTDE and the secondary interface at its options' ports: the printed
    # link URL carries those not at the defaults, so the hint works as printed; a cell.toml
    # gives them as the machine's options.
    secondary, rtde = ports["secondary"], ports["rtde"]
    hint = drive_command(emulator.dashboard_url, secondary, rtde)
    console.print(f"  drive it with: {hint}", soft_wrap=True)
    usual = UrOptions()
    if (secondary, rtde) != (usual.secondary_port, usual.rtde_port):
        console.print(
            f'  or from a cell.toml: kind = "ur", link = "{emulator.dashboard_url}", '
            f"options = {{ secondary_port = {secondary}, rtde_port = {rtde} }}",
            soft_wrap=True,
        )


def _robot_command(function: str, doc: str) -> click.Command:
    """``cellctl robot FUNCTION``: one of the UR's functions on the named machine."""

    @click.pass_context
    def callback(ctx: click.Context) -> None:
        from cellctl.ui.calls import machine_call

        result = machine_call(ctx, "robot", function, {})
        for line in result.get("lines", []):
            console.print(line, markup=False)
        console.print(result["message"], markup=False)

    return click.Command(function, callback=callback, help=doc)  # the API method's name


#: The UR's functions the IBM robot's command group does not have (``cellctl robot unlock``).
ROBOT_COMMANDS = [_robot_command(name, doc) for name, doc in ROBOT_FUNCTIONS.items()]
