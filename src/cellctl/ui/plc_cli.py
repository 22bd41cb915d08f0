"""``cellctl plc`` (read and switch the cell PLC's signals) and ``cellctl emulate plc``.

The PLC and its IO map come from ``[plc]`` in the cell's ``cell.toml`` (assumed defaults if
there is none); ``--url`` overrides where it is::

    cellctl plc status                          # every input and coil, with its meaning
    cellctl plc --url modbus://10.0.0.9 set door_1 1
    cellctl plc pulse go_2 --seconds 0.5
    cellctl emulate plc --listen modbus://127.0.0.1:5020 --time-scale 10 --fault no-pallet
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import click

from cellctl.drivers.state import StateStore
from cellctl.emulators.plc import FAULTS, PlcEmulator
from cellctl.emulators.serve import MACHINE_TIME_SCALE, TIME_SCALE_HELP
from cellctl.protocol.plc import SIGNALS, PlcMap
from cellctl.service.machines import load_cell_file
from cellctl.ui.common import cell_dir, console, fault_help, run, stop_signals


def _quiet_pymodbus() -> None:
    # pymodbus logs each failure it hands back; the command prints it once, as a typed error.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def plc_map_for(ctx: click.Context, url: str | None) -> PlcMap:
    """The ``[plc]`` map of the cell's ``cell.toml`` (defaults if none), at ``url`` if given."""
    _quiet_pymodbus()
    table = dict(load_cell_file(cell_dir(ctx)).get("plc", {}))
    if url:
        table["url"] = url
    return PlcMap.from_toml(table)


@click.group()
@click.option("--url", help="PLC address, modbus://HOST[:PORT] (default: [plc] in cell.toml).")
@click.option("--timeout", type=float, help="Seconds each request may take.")
@click.pass_context
def plc(ctx: click.Context, url: str | None, timeout: float | None) -> None:
    """The cell PLC over Modbus/TCP: sensors (inputs) and actuators (coils)."""
    ctx.ensure_object(dict)
    ctx.obj["plc_url"] = url
    ctx.obj["plc_timeout"] = timeout


def _target(ctx: click.Context) -> tuple[PlcMap, float | None]:
    obj = ctx.find_object(dict) or {}
    return plc_map_for(ctx, obj.get("plc_url")), obj.get("plc_timeout")


def _store(ctx: click.Context) -> StateStore | None:
    """The cell's state store (its PLC lock), if the cell directory exists: a running
    controller holds the PLC, and these commands are refused rather than act beside it.

    None for a ``--url`` that is not the cell's PLC (another PLC, one being tried before
    cell.toml names it): the cell's lock is not its own, and its URL lock still excludes
    every other opener of that PLC."""
    from cellctl.link.keys import links_overlap

    directory = cell_dir(ctx)
    if not directory.is_dir():
        return None
    url = (ctx.find_object(dict) or {}).get("plc_url")
    if url and not links_overlap(url, plc_map_for(ctx, None).url):
        return None
    return StateStore(directory)


@plc.command()
@click.pass_context
def status(ctx: click.Context) -> None:
    """Show every input and coil: level, address, meaning (through the running controller,
    which holds the PLC, when one runs the cell)."""
    from cellctl.cell.owner import controller_holder

    obj = ctx.find_object(dict) or {}
    if obj.get("plc_url") is None and controller_holder(cell_dir(ctx)) is not None:
        from cellctl.ui.calls import cell_call

        _print_status(cell_call(ctx, "plc.status"))
        return

    async def main() -> dict[str, Any]:
        from cellctl.drivers.plc import ModbusPlc

        plc_map, timeout = _target(ctx)  # inside run(): a bad [plc] table is a usage error

        async with await ModbusPlc.connect(
            plc_map.url, plc_map, timeout=timeout, store=_store(ctx)
        ) as driver:
            read = {"inputs": await driver.read_inputs(), "coils": await driver.read_coils()}
        addresses = {"inputs": plc_map.inputs, "coils": plc_map.coils}
        return {
            "url": plc_map.url,
            "unit": plc_map.unit,
            **{
                kind: {
                    name: {"level": level, "address": addresses[kind][name]}
                    for name, level in levels.items()
                }
                for kind, levels in read.items()
            },
        }

    _print_status(run(main))


def _print_status(found: dict[str, Any]) -> None:
    """``plc status``'s lines, from the PLC read here or through the API (``plc.status``)."""
    console.print(f"PLC at {found['url']} (unit {found['unit']})")
    for kind in ("inputs", "coils"):
        console.print(f"{kind}:")
        for name, signal in found[kind].items():
            console.print(
                f"  {name:<16} {int(signal['level'])}  @{signal['address']:<5} "
                f"{SIGNALS[name].meaning}"
            )


@plc.command("set")
@click.argument("name")
@click.argument("value", type=click.Choice(["0", "1"]))
@click.pass_context
def set_coil(ctx: click.Context, name: str, value: str) -> None:
    """Set coil NAME to 0 or 1 (e.g. ``set door_1 1`` opens the door of CNC 1)."""

    async def main() -> None:
        from cellctl.drivers.plc import ModbusPlc

        plc_map, timeout = _target(ctx)  # inside run(): a bad [plc] table is a usage error

        plc_map.kind_of(name)  # an unknown name is refused before connecting
        async with await ModbusPlc.connect(
            plc_map.url, plc_map, timeout=timeout, store=_store(ctx)
        ) as driver:
            await driver.write(name, value == "1")
        console.print(f"{name} = {value}")

    run(main)


@plc.command()
@click.argument("name")
@click.option("--seconds", type=float, default=0.5, show_default=True, help="Pulse length.")
@click.pass_context
def pulse(ctx: click.Context, name: str, seconds: float) -> None:
    """Set coil NAME to 1 for a moment, then 0 (e.g. ``pulse go_1`` starts CNC 1)."""

    async def main() -> None:
        from cellctl.drivers.plc import ModbusPlc

        plc_map, timeout = _target(ctx)  # inside run(): a bad [plc] table is a usage error

        plc_map.kind_of(name)
        async with await ModbusPlc.connect(
            plc_map.url, plc_map, timeout=timeout, store=_store(ctx)
        ) as driver:
            await driver.pulse(name, seconds)
        console.print(f"{name} pulsed for {seconds:g} s")

    run(main)


@click.command("plc", help="Emulate the cell PLC (Modbus/TCP).\n\n" + fault_help(FAULTS))
@click.option(
    "--listen",
    default=None,
    help="modbus://HOST:PORT (port 0: a free one). Default: [plc] url in cell.toml.",
)
@click.option(
    "--time-scale",
    type=float,
    default=MACHINE_TIME_SCALE,
    show_default=True,
    help="Machine times divided by this (10 = ten times faster). " + TIME_SCALE_HELP,
)
@click.option("--fault", multiple=True, metavar="NAME[=ARG]", help="Fault switch.")
@click.pass_context
def emulate_plc(
    ctx: click.Context, listen: str | None, time_scale: float, fault: tuple[str, ...]
) -> None:
    """Serve an emulated PLC until Ctrl-C or SIGTERM."""

    async def main() -> None:
        plc_map = plc_map_for(ctx, listen)
        # Here, not at the top: `cellctl plc` reads and switches signals, and serves nothing.
        from cellctl.ui.emulate_cli import say_faults, switch_faults

        device = PlcEmulator(plc_map, time_scale=time_scale)
        said = switch_faults(device, FAULTS, fault)
        # Ctrl-C and SIGTERM taken before anything is printed: whoever reads what it says
        # and stops it at once gets the same clean stop as later.
        stop = asyncio.Event()
        with stop_signals(stop):
            url = await device.start(plc_map.url)
            try:
                console.print(f"PLC emulator listening on {url}  (unit any, time x{time_scale:g})")
                console.print(f"  drive it with: cellctl plc --url {url} status")
                backend = device.backend_url
                console.print(f"  behind it, pymodbus on {backend} (no fault switch acts there)")
                say_faults(said)
                await stop.wait()
            finally:
                await device.close()
                console.print("PLC emulator stopped")

    run(main)
