"""``cellctl dnc``: the DNC server and its hand commands (docs/dnc.md).

::

    cellctl dnc serve --dir SHOP                 # every machine of SHOP/dnc.toml
    cellctl dnc send  mill1 O1234 --dir SHOP     # into the control's memory, with progress
    cellctl dnc drip  mill1 big.nc --dir SHOP    # drip-feed (the control runs as it reads)
    cellctl dnc receive mill1 --dir SHOP         # keep what the control punches
    cellctl dnc stop  mill1 --dir SHOP           # stop the transfer in flight
    cellctl dnc diff  mill1 O1234 --dir SHOP     # the newest received O1234 against the sent
    cellctl dnc status --dir SHOP

When a ``dnc serve`` runs on SHOP, the hand commands go through its control API (its Unix
socket ``SHOP/api.sock`` and token ``SHOP/api-token``); otherwise they open the machine's link
themselves, under the same owner locks (a second opener is refused, naming the holder).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
from rich.progress import BarColumn, TextColumn, TimeRemainingColumn

from cellctl.ui.common import (
    cell_dir,
    console,
    err_console,
    json_option,
    print_json,
    run,
    stop_signals,
)

if TYPE_CHECKING:
    from cellctl.kinds.iso_cnc.dnc.config import ShopConfig

# The server, the API and the links are imported by the command that uses them: `cellctl
# --help` and a refused argument load none of them (tests/test_cli_startup.py).


def _shop_options(f: Callable[..., Any]) -> Callable[..., Any]:
    f = click.option(
        "--use-cell",
        is_flag=True,
        help="Feed the iso-cnc machines of the cell's cell.toml (--cell) instead of dnc.toml.",
    )(f)
    return click.option(
        "--dir",
        "shop",
        envvar="CELLCTL_SHOP",
        default="shop",
        show_default=True,
        type=click.Path(file_okay=False, path_type=Path),
        help="The shop directory: dnc.toml, one directory per machine.",
    )(f)


def _config(ctx: click.Context, shop: Path, use_cell: bool) -> ShopConfig:
    from cellctl.kinds.iso_cnc.dnc.config import load_shop

    return load_shop(shop, cell=cell_dir(ctx) if use_cell else None)


@click.group("dnc")
def dnc() -> None:
    """DNC server for the shop's ISO-code CNC controls (Fanuc / Haas style, RS-232)."""


# -- serve -------------------------------------------------------------------------------------


@dnc.command()
@_shop_options
@click.pass_context
def serve(ctx: click.Context, shop: Path, use_cell: bool) -> None:
    """Feed every machine: answer remote requests, keep what the controls punch."""
    config = _config(ctx, shop, use_cell)
    run(lambda: serve_shop(config))


async def serve_shop(config: ShopConfig, *, stop: asyncio.Event | None = None) -> None:
    """Serve ``config``'s machines and its API until ``stop`` is set (or SIGINT / SIGTERM)."""
    from cellctl.cell.owner import acquire_controller_lock
    from cellctl.kinds.iso_cnc.dnc.access import DncAccess
    from cellctl.kinds.iso_cnc.dnc.server import DncServer
    from cellctl.service.server import ApiServer
    from cellctl.ui.dashboard.routes import dashboard_routes

    config.root.mkdir(mode=0o700, parents=True, exist_ok=True)
    stop = stop or asyncio.Event()
    with acquire_controller_lock(config.root):
        server = DncServer(config)
        api = ApiServer(
            DncAccess(server),
            config.root,
            listen=config.listen,
            allow_remote=config.allow_remote,
            extra_routes=dashboard_routes,
        )
        server.listeners.append(api.changed)
        # Ctrl-C, SIGTERM: ours from here, as found again once the finally below begins.
        signals = contextlib.ExitStack()
        signals.enter_context(stop_signals(stop.set))
        try:
            await server.start()
            await api.start()
            names = ", ".join(sorted(config.machines))
            console.print(f"DNC server: {names}; control API on {api.url}", markup=False)
            await stop.wait()
        finally:
            signals.close()
            await api.close()
            await server.close()


# -- by hand -----------------------------------------------------------------------------------


async def call_shop(
    config: ShopConfig,
    name: str,
    method: str,
    params: dict[str, Any],
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> Any:
    """``method`` on machine ``name``: through the running server's API, or on the link
    opened here (under its owner locks) when no server runs on the shop."""
    from cellctl.cell.owner import controller_holder
    from cellctl.kinds.iso_cnc.dnc.access import DncAccess
    from cellctl.kinds.iso_cnc.dnc.config import machine
    from cellctl.kinds.iso_cnc.dnc.server import TRANSFER_S, DncServer
    from cellctl.service.client import attach
    from cellctl.service.methods import Dispatcher

    machine(config, name)
    params = {"machine": name, **params}
    if controller_holder(config.root) is not None:
        async with await attach(config.root) as api:
            return await api.call(method, params, progress, timeout=TRANSFER_S)
    one = dataclasses.replace(config, machines={name: config.machines[name]})
    server = DncServer(one)
    await server.start()  # the machine's own task listens, as under `dnc serve`
    try:
        return await Dispatcher(DncAccess(server)).call(method, params, progress)
    finally:
        await server.close()


def _bar_columns() -> tuple[Any, ...]:
    return (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f} chars"),
        TextColumn("{task.fields[rate]:>6.0f} chars/s"),
        TextColumn("{task.fields[stops]} buffer stops"),
        TextColumn("{task.fields[phase]}"),
        TimeRemainingColumn(),
    )


def _fields(p: dict[str, Any], elapsed: float) -> dict[str, Any]:
    return {
        "total": max(1, p["chars_total"]),
        "completed": p["chars_sent"],
        "rate": p["chars_per_s"],
        "stops": p["buffer_stops"],
        "phase": p["phase"],
    }


def _transfer(
    ctx: click.Context, shop: Path, use_cell: bool, name: str, program: str, drip: bool
) -> None:
    from cellctl.kinds.iso_cnc.dnc.config import machine
    from cellctl.kinds.iso_cnc.dnc.store import ShopStore, read_program_file
    from cellctl.kinds.iso_cnc.driver import prepare
    from cellctl.ui.calls import LazyBar

    config = _config(ctx, shop, use_cell)
    params: dict[str, Any] = {"program": program, "drip": drip}
    path = Path(program)
    if path.is_file():  # a file here: its text travels (the server may not see this path)
        params = {"program": path.name, "drip": drip, "text": read_program_file(path).decode()}
    else:
        ShopStore(config.root).resolve(name, program)  # refused here, before a byte goes out
    text = params.get("text")
    if text is None:
        text = read_program_file(ShopStore(config.root).resolve(name, program)).decode()
    # the G-code check with the machine's options: refused here, before a byte goes out
    prepare(text.encode("ascii"), machine(config, name).options, params["program"])
    what = "drip-feed" if drip else "read-in"
    err_console.print(
        f"{name}: {what} of {params['program']}: start the read on the control "
        "(READ in EDIT, or CYCLE START in RMT/DNC)",
        markup=False,
    )
    with LazyBar(_bar_columns(), params["program"], _fields) as bar:
        result = run(lambda: call_shop(config, name, "dnc.send", params, bar.update))
    console.print(result["message"], markup=False)


@dnc.command()
@click.argument("name", metavar="MACHINE")
@click.argument("program")
@_shop_options
@click.pass_context
def send(ctx: click.Context, name: str, program: str, shop: Path, use_cell: bool) -> None:
    """Send PROGRAM (a file, or O1234 of the machine's programs/) into the control's memory."""
    _transfer(ctx, shop, use_cell, name, program, drip=False)


@dnc.command()
@click.argument("name", metavar="MACHINE")
@click.argument("program")
@_shop_options
@click.pass_context
def drip(ctx: click.Context, name: str, program: str, shop: Path, use_cell: bool) -> None:
    """Drip-feed PROGRAM: the control runs it as it arrives (RMT / DNC mode)."""
    _transfer(ctx, shop, use_cell, name, program, drip=True)


@dnc.command()
@click.argument("name", metavar="MACHINE")
@click.option("--timeout", type=float, default=600.0, show_default=True, help="Seconds to wait.")
@_shop_options
@click.pass_context
def receive(ctx: click.Context, name: str, timeout: float, shop: Path, use_cell: bool) -> None:
    """Keep what the control punches (select the program, press PUNCH on the control)."""
    config = _config(ctx, shop, use_cell)
    err_console.print(f"{name}: waiting for the control: press PUNCH on it", markup=False)
    result = run(lambda: call_shop(config, name, "dnc.receive", {"timeout": timeout}))
    for item in result["programs"]:
        if "refused" in item:
            console.print(f"refused: {item['refused']}", markup=False)
        elif "request" in item:
            console.print(f"request: {item['request']}", markup=False)
        else:
            console.print(f"received O{item['program']:04d}: {item['kept']}", markup=False)


@dnc.command("stop")
@click.argument("name", metavar="MACHINE")
@_shop_options
@click.pass_context
def stop_transfer(ctx: click.Context, name: str, shop: Path, use_cell: bool) -> None:
    """Stop the read-in or drip-feed in flight on MACHINE (or drop the request waiting for
    its read). The control is left mid-read: reset it before its next read."""
    config = _config(ctx, shop, use_cell)
    result = run(lambda: call_shop(config, name, "dnc.stop", {}))
    console.print(result["message"], markup=False)


@dnc.command()
@click.argument("name", metavar="MACHINE")
@click.argument("received", required=False)
@click.option("--against", help="The sent file to compare with (default: the last O-number sent).")
@click.option("--ignore-spaces", is_flag=True, help="Spaces inside blocks do not count.")
@_shop_options
@click.pass_context
def diff(
    ctx: click.Context,
    name: str,
    received: str | None,
    against: str | None,
    ignore_spaces: bool,
    shop: Path,
    use_cell: bool,
) -> None:
    """Compare a received program (a file or O1234: its newest copy) with what was sent.

    Exit 0 when they match, 1 when they differ.
    """
    from cellctl.kinds.iso_cnc.dnc.diff import compare
    from cellctl.kinds.iso_cnc.dnc.store import ShopStore, read_program_file

    store = ShopStore(shop)
    if received is not None and Path(received).is_file():
        got = Path(received)
        number = None
    else:
        wanted = None if received is None else int(received.lstrip("Oo:") or "x")
        copies = store.received(name, wanted)
        if not copies:
            raise click.UsageError(f"no received program {received or ''} for {name}".strip())
        got, number = copies[-1].path, copies[-1].number
    if against is not None:
        sent_path = Path(against)
    else:
        from cellctl.kinds.iso_cnc.tape import o_number, unframe

        number = number if number is not None else o_number(unframe(read_program_file(got)))
        sent = store.sent(name, number) if number is not None else []
        if not sent:
            raise click.UsageError(f"nothing sent to {name} as O{number or 0:04d}: give --against")
        sent_path = sent[-1].path
    result = compare(
        read_program_file(sent_path),
        read_program_file(got),
        sent_name=str(sent_path),
        received_name=str(got),
        spaces=not ignore_spaces,
    )
    if result.same:
        console.print(f"{got.name} matches {sent_path.name} ({result.blocks_sent} blocks)")
        return
    console.print(result.text, markup=False, soft_wrap=True)
    sys.exit(1)


@dnc.command()
@_shop_options
@json_option
@click.pass_context
def status(ctx: click.Context, shop: Path, use_cell: bool, as_json: bool) -> None:
    """Each machine's state: through the running server, else its log's last line."""
    from cellctl.cell.owner import controller_holder
    from cellctl.kinds.iso_cnc.dnc.store import ShopStore
    from cellctl.service.client import attach

    config = _config(ctx, shop, use_cell)
    if controller_holder(config.root) is None:
        store = ShopStore(config.root)
        logged = {name: store.log_lines(name, 1) for name in sorted(config.machines)}
        if as_json:
            print_json(
                {
                    n: {"server": False, "log": last[0] if last else None}
                    for n, last in logged.items()
                }
            )
            return
        for name, last in logged.items():
            console.print(f"{name}: no server runs; {last[0] if last else 'no log'}", markup=False)
        return

    async def main() -> dict[str, Any]:
        async with await attach(config.root) as api:
            answer: dict[str, Any] = await api.call("cell.status")
            return answer

    machines = dict(sorted(run(main)["machines"].items()))
    if as_json:
        print_json(machines)
        return
    for name, m in machines.items():
        console.print(f"{name}: {m['condition']}: {m['state']}", markup=False)
