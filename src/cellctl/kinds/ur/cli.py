"""``cellctl emulate ur``: a UR controller's three interfaces on this machine."""

from __future__ import annotations

from pathlib import Path

import click

from cellctl.emulators.serve import parse_fault
from cellctl.errors import UsageError
from cellctl.kinds.ur.emulator import FAULTS, UrEmulator
from cellctl.kinds.ur.motion import ARMS
from cellctl.ui.common import console, fault_help, run


def _programs(items: tuple[str, ...]) -> dict[str, str]:
    out = {}
    for item in items:
        path, sep, file = item.partition("=")
        if not sep or not path.endswith(".urp"):
            raise UsageError(f"--program takes ROBOT_PATH.urp=SCRIPT_FILE, not {item!r}")
        try:
            out[path] = Path(file).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise UsageError(f"{file}: cannot read it: {e}") from None
    return out


@click.command("ur", help="Emulate a Universal Robots controller: Dashboard Server, "
               "secondary interface and RTDE.\n\n" + fault_help(FAULTS))  # fmt: skip
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to listen on.")
@click.option("--dashboard-port", default=29999, show_default=True)
@click.option("--secondary-port", default=30002, show_default=True)
@click.option("--rtde-port", default=30004, show_default=True)
@click.option("--model", type=click.Choice(sorted(ARMS)), default="UR5e", show_default=True)
@click.option(
    "--time-scale", default=1.0, show_default=True, help="Machine time runs this much faster."
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
        from cellctl.ui.common import until_stopped

        emulator = UrEmulator(time_scale=time_scale, model=model, programs=_programs(programs))
        for text in fault:
            emulator.set_fault(*parse_fault(text))
        ports = await emulator.start(
            host, dashboard=dashboard_port, secondary=secondary_port, rtde_port=rtde_port
        )
        console.print(f"UR emulator ({model}, time scale {time_scale:g}) on {host}")
        console.print(
            f"  ports: dashboard {ports['dashboard']}, secondary {ports['secondary']}, "
            f"RTDE {ports['rtde']}"
        )
        console.print(f"  drive it with: --link {emulator.dashboard_url}")
        try:
            await until_stopped()
        finally:
            await emulator.close()

    run(main)
