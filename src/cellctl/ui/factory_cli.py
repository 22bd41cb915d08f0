"""The system controller from the shell: ``cellctl factory [--dir DIR]
submit|cancel|orders|cells|run``, the cell's commands one level up, and ``cellctl emulate
factory --cells N [--template CELL]... DIR``.

``submit [--due WHEN]`` queues an order (due then: its cell gets the due time with it, and
``orders`` shows it, LATE once past); ``submit``, ``cancel`` and ``orders`` read and write the
factory's store
(``DIR/state/factory.db``) whether or not ``run`` runs: ``run`` picks a new order or a cancel
up within 20 ms. ``run`` is the one factory controller of DIR (a second one is refused, naming
the first).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import time
from collections import Counter
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

import click
from rich.console import Group
from rich.live import Live
from rich.table import Table

from cellctl.clock import current_clock
from cellctl.emulators.serve import CELL_TIME_SCALE, TIME_SCALE_HELP
from cellctl.errors import UsageError
from cellctl.factory.cancel import request_cancel
from cellctl.factory.config import FactoryConfig, factory_lock_path, load_factory
from cellctl.factory.dispatch import load_s
from cellctl.factory.store import (
    CANCELLING,
    OPEN_STATES,
    CellSeen,
    FactoryOrder,
    FactoryStore,
)
from cellctl.link.lock import OwnerLock
from cellctl.ui.common import (
    console,
    json_option,
    print_json,
    print_table,
    run,
    stop_signals,
    until_stopped,
)
from cellctl.ui.emulate_cli import TIME_SCALE
from cellctl.ui.factory_plan_cli import factory_plan
from cellctl.ui.orders_cli import STATE_STYLE, checked_due, due_option

if TYPE_CHECKING:
    from cellctl.factory.controller import FactoryController

#: What a second factory controller is told.
ALREADY_RUN = "the factory in {what} is already run by {holder}"


def _styled(state: str) -> str:
    style = STATE_STYLE.get(state, {"sent": "cyan", CANCELLING: "magenta"}.get(state))
    return f"[{style}]{state}[/{style}]" if style else state


def _config(ctx: click.Context) -> FactoryConfig:
    return load_factory(Path(ctx.obj["factory_dir"]))


@click.group("factory")
@click.option(
    "--dir",
    "directory",
    type=click.Path(file_okay=False),
    default="factory",
    show_default=True,
    help="Factory directory: factory.toml and the factory's state.",
)
@click.pass_context
def factory(ctx: click.Context, directory: str) -> None:
    """The system controller: orders spread over the cells through an MQTT broker."""
    ctx.obj = {**(ctx.obj or {}), "factory_dir": directory}


@factory.command("submit")
@click.argument("part_type", metavar="PART")
@click.option(
    "--qty", type=click.IntRange(min=1), default=1, show_default=True, help="How many parts."
)
@click.option("--priority", type=int, default=0, show_default=True, help="Higher goes first.")
@click.option("--id", "order_id", metavar="ID", help="The order's id (the same id again: no-op).")
@due_option("this host's clock", " Its cell gets it with the order.")
@click.pass_context
def submit(
    ctx: click.Context,
    part_type: str,
    qty: int,
    priority: int,
    order_id: str | None,
    due: str | None,
) -> None:
    """Submit an order for QTY parts of type PART; the factory gives it to a cell."""
    from cellctl.service.orderdue import due_words

    now = current_clock().now()
    due_at = checked_due(due, now)  # before the store is opened: nothing recorded or sent

    async def main() -> None:
        config = _config(ctx)
        with FactoryStore(config.state_path) as store:
            made = {t for c in store.cells().values() for t in c.part_types}
            if made and part_type not in made:
                raise UsageError(
                    f"no cell makes {part_type!r} (the cells make: {', '.join(sorted(made))})"
                )
            order, new = store.submit(part_type, qty, priority, order_id, due=due_at)
        asked = (part_type, qty, priority, due_at)
        if not new and (order.part_type, order.qty, order.priority, order.due) != asked:
            # The same id for another order: a retry must ask the same, or it is a mistake
            # (as a cell's `cellctl submit` says it).
            raise UsageError(
                f"order {order.id} was submitted before as "
                f"{_what(order.qty, order.part_type, order.priority, order.due)}, not "
                f"{_what(qty, part_type, priority, due_at)}: nothing changed (give this order "
                "another --id)"
            )
        what = "submitted" if new else "already submitted (unchanged)"
        console.print(
            f"order {order.id} {what}: {order.qty} x {order.part_type}{due_words(order.due, now)}",
            markup=False,
            soft_wrap=True,
        )

    run(main)


def _what(qty: int, part_type: str, priority: int, due: float | None) -> str:
    """An order as a refusal names it: ``2 × wax-robot-base, priority 0, due Fri ...``."""
    from cellctl.plan.when import when_text

    shown = "" if due is None else f", due {when_text(due, date=True)}"
    return f"{qty} × {part_type}, priority {priority}{shown}"


@factory.command("cancel")
@click.argument("order_id", metavar="ORDER")
@click.option("--reason", default="", help="Why, kept with the cancel (at most 500 characters).")
@click.pass_context
def cancel(ctx: click.Context, order_id: str, reason: str) -> None:
    """Cancel order ORDER: at once if it is at no cell, else through its cell, which cancels
    it as its operator would (only an order none of whose parts has started); the order shows
    as cancelling until the cell says so. A done, failed or cancelled order is refused."""

    async def main() -> None:
        config = _config(ctx)
        with FactoryStore(config.state_path) as store:
            asked = request_cancel(store, order_id, reason=reason)
        console.print(asked.message, markup=False, soft_wrap=True)

    run(main)


def hms(seconds: float) -> str:
    """Seconds as h:mm:ss (``2560.7`` → ``0:42:41``)."""
    whole = max(0, round(seconds))
    return f"{whole // 3600}:{whole % 3600 // 60:02d}:{whole % 60:02d}"


#: Orders the live view shows at most (the open ones first, then the latest ended).
LIVE_ORDERS = 15


def live_orders(orders: list[FactoryOrder], limit: int) -> tuple[list[FactoryOrder], int]:
    """What a view of ``limit`` rows shows of ``orders``: every open one first (as the store
    gives them: highest priority, then oldest), then the latest ended; and how many it leaves
    out."""
    open_ones = [o for o in orders if o.state in OPEN_STATES]
    ended = sorted(
        (o for o in orders if o.state not in OPEN_STATES),
        key=lambda o: (o.finished or o.updated, o.submitted),
        reverse=True,
    )
    shown = [*open_ones, *ended][:limit]
    return shown, len(orders) - len(shown)


def is_late(order: FactoryOrder, now: float) -> bool:
    """Whether ``order`` is late at ``now``, by the cell's rule (``cellctl orders``' LATE):
    done after its due time, or not done and past it; never without one, or cancelled."""
    from cellctl.service.orderdue import is_late as late_by_the_cells_rule

    ended = order.finished if order.finished is not None else order.updated
    return late_by_the_cells_rule(order.state, ended, order.due, now)


def due_text(order: FactoryOrder, now: float) -> str:
    """The due column's text: ``2026-12-04 18:00:00``, ``LATE`` after it when late; "" for
    an order without a due time."""
    if order.due is None:
        return ""
    when = datetime.fromtimestamp(order.due).strftime("%Y-%m-%d %H:%M:%S")
    return when + (" [red]LATE[/red]" if is_late(order, now) else "")


def orders_table(rows: list[FactoryOrder], *, more: str = "") -> Table:
    """One line per order of ``rows``; ``more``: a last line saying what is left out. A due
    column when an order of them has a due time (else the table as it always was)."""
    table = Table(title="orders", expand=True, caption=more or None, caption_justify="left")
    dues = any(o.due is not None for o in rows)
    columns = ("order", "part", "qty", "state", "cell", "done", "held", *("due",) * dues)
    for col in columns:
        # The note keeps at least a third of the width: it says why an order waits.
        table.add_column(col, overflow="fold", ratio=1 if col in ("order", "part") else None)
    table.add_column("note", overflow="fold", ratio=2, min_width=20)
    now = current_clock().now()
    for o in rows:
        table.add_row(
            o.id,
            o.part_type,
            str(o.qty),
            _styled(o.shown_state),
            o.cell or "",
            str(o.done),
            str(o.held),
            *(due_text(o, now),) * dues,
            o.note,
        )
    return table


def _machines(c: CellSeen) -> dict[str, dict[str, object]]:
    return dict(c.state.get("machines") or {})


def _machines_summary(c: CellSeen) -> str:
    """``3 machines: 2 idle, 1 busy; cnc2 OUT``: the states counted, out-of-service by name."""
    machines = _machines(c)
    counts = Counter(str(v.get("state", "?")) for v in machines.values())
    text = f"{len(machines)}: " + ", ".join(f"{n} {state}" for state, n in counts.items())
    out = [m for m, v in machines.items() if not v.get("in_service", True)]
    return text + (f"; {', '.join(out)} OUT" if out else "")


def cells_table(store: FactoryStore, config: FactoryConfig, wide: bool = False) -> Table:
    """One line per cell; its machines counted by state (``wide``: each machine by name)."""
    table = Table(title="cells", expand=True)
    for col in ("cell", "status", "open", "parts", "work left"):
        table.add_column(col, no_wrap=True)
    table.add_column("makes", overflow="fold", ratio=1)
    table.add_column("machines", overflow="fold", ratio=1)
    seen = store.cells()
    open_orders = store.orders(OPEN_STATES)
    for name in config.cells:
        c = seen.get(name)
        if c is None:
            table.add_row(name, "never heard", "", "", "", "", "")  # no state yet
            continue
        status = f"[green]{c.status}[/green]" if c.status == "online" else f"[red]{c.status}[/red]"
        if c.state.get("paused"):
            status += " (paused)"
        if wide:
            machines = ", ".join(
                f"{m}: {v.get('state', '?')}" + ("" if v.get("in_service", True) else " OUT")
                for m, v in _machines(c).items()
            )
        else:
            machines = _machines_summary(c)
        table.add_row(
            name,
            status,
            str(sum(1 for o in open_orders if o.cell == name)),
            str(c.state.get("parts_open", "")),
            hms(load_s(c, open_orders)) if c.state else "",
            ", ".join(c.part_types),
            machines,
        )
    return table


def cells_json(store: FactoryStore, config: FactoryConfig) -> list[dict[str, object]]:
    """The cells as :func:`cells_table` shows them, every machine in full, for scripts."""
    seen = store.cells()
    open_orders = store.orders(OPEN_STATES)
    found: list[dict[str, object]] = []
    for name in config.cells:
        c = seen.get(name)
        if c is None:
            found.append({"cell": name, "status": "never heard"})
            continue
        found.append(
            {
                "cell": name,
                "status": c.status,
                "paused": bool(c.state.get("paused")),
                "open_orders": sum(1 for o in open_orders if o.cell == name),
                "parts_open": c.state.get("parts_open"),
                "work_left_s": load_s(c, open_orders) if c.state else None,
                "makes": list(c.part_types),
                "machines": _machines(c),
            }
        )
    return found


@factory.command("orders")
@click.option("--open", "only_open", is_flag=True, help="Only orders not yet ended.")
@json_option
@click.pass_context
def orders(ctx: click.Context, only_open: bool, as_json: bool) -> None:
    """The factory's orders: where each went and how far it is."""

    async def main() -> None:
        config = _config(ctx)
        with FactoryStore(config.state_path) as store:
            rows = store.orders(None if not only_open else OPEN_STATES)
            if as_json:
                now = current_clock().now()
                print_json(
                    [
                        {
                            **dataclasses.asdict(o),
                            "cancelling": o.cancelling,
                            "late": is_late(o, now),
                        }
                        for o in rows
                    ]
                )
                return
            if not rows:
                console.print("no open orders" if only_open else "no orders", markup=False)
                return
            print_table(orders_table(rows))  # every one: a pipe or a pager takes them all

    run(main)


@factory.command("cells")
@click.option("--wide", is_flag=True, help="Each machine's state by name, not counted.")
@json_option
@click.pass_context
def cells(ctx: click.Context, wide: bool, as_json: bool) -> None:
    """The cells as the factory last heard them: online, what they make, their work left."""

    async def main() -> None:
        config = _config(ctx)
        with FactoryStore(config.state_path) as store:
            if as_json:
                print_json(cells_json(store, config))
                return
            print_table(cells_table(store, config, wide=wide))

    run(main)


def live_view(store: FactoryStore, config: FactoryConfig) -> Group:
    events = Table(title="events", expand=True, show_header=False)
    events.add_column("time", width=10)
    events.add_column("event")
    for e in store.events(limit=8):
        events.add_row(datetime.fromtimestamp(e.time).strftime("%H:%M:%S"), e.text)
    shown, left = live_orders(store.orders(), LIVE_ORDERS)
    more = f"… {left} more: cellctl factory --dir {config.directory} orders" if left else ""
    return Group(cells_table(store, config), orders_table(shown, more=more), events)


async def run_factory(
    directory: Path,
    *,
    live: bool,
    until_idle: bool,
    stop: asyncio.Event | None = None,
    on_controller: list[FactoryController] | None = None,
) -> None:
    """Run the factory controller of ``directory`` until stopped (or every order ended)."""
    from cellctl.factory.controller import FactoryController  # the broker client: when run

    config = load_factory(directory)
    lock_path = factory_lock_path(config.directory)
    lock_path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    with (
        OwnerLock.acquire(lock_path, str(directory), refusal=ALREADY_RUN),
        FactoryStore(config.state_path) as store,
    ):
        stop = stop or asyncio.Event()
        printer = None if live else _print
        controller = FactoryController(config, store, log=printer or (lambda text: None))
        if on_controller is not None:
            on_controller.append(controller)
        # Ctrl-C, SIGTERM: ours from here, as found again once the finally below begins.
        signals = contextlib.ExitStack()
        signals.enter_context(stop_signals(stop.set))
        try:
            task = asyncio.create_task(controller.run(stop, until_idle=until_idle))
            if live:
                with Live(live_view(store, config), console=console, refresh_per_second=4) as s:
                    while not task.done():
                        s.update(live_view(store, config))
                        await asyncio.wait({task}, timeout=0.25)
                    s.update(live_view(store, config))
            await task
        finally:
            signals.close()


def _print(text: str) -> None:
    stamp = time.strftime("%H:%M:%S", time.localtime(current_clock().now()))
    console.print(f"{stamp} {text}", markup=False, soft_wrap=True)
    console.file.flush()


@factory.command("run")
@click.option(
    "--live/--no-live",
    default=None,
    help="Live view of cells and orders, or an event a line (the default off a terminal).",
)
@click.option("--until-idle", is_flag=True, help="Return once every order has ended.")
@click.pass_context
def run_command(ctx: click.Context, live: bool | None, until_idle: bool) -> None:
    """Run the factory controller: dispatch orders, follow them, show cells and orders live."""
    directory = Path(ctx.obj["factory_dir"])
    live_on = console.is_terminal if live is None else live
    run(lambda: run_factory(directory, live=live_on, until_idle=until_idle))


@click.command("factory")
@click.option(
    "--cells",
    "count",
    type=click.IntRange(1, 32),
    metavar="N",
    default=None,
    help="How many emulated cells  [default: 3, or as many as --template given]",
)
@click.option(
    "--template",
    "templates",
    multiple=True,
    type=click.Path(file_okay=False, exists=True),
    metavar="DIR",
    help="A cell directory to emulate (its machines, programs and part types), once per "
    "cell: cell1 the first given, cell2 the second...; the cells past them emulate the "
    "example cell. Repeat it, e.g. --template examples/cell-tending --template examples/cell.",
)
@click.option(
    "--time-scale",
    type=TIME_SCALE,
    default=CELL_TIME_SCALE,
    show_default=True,
    help="Machine time runs this many times faster than real (1: real time). " + TIME_SCALE_HELP,
)
@click.option(
    "--accept-timeout",
    type=float,
    default=30.0,
    show_default=True,
    help="Seconds a cell has to accept an order before the factory gives it to another.",
)
@click.argument("directory", type=click.Path(file_okay=False))
def emulate_factory(
    count: int | None,
    templates: tuple[str, ...],
    time_scale: float,
    accept_timeout: float,
    directory: str,
) -> None:
    """Start a private Mosquitto and the emulated cells (--cells N of them); write their cell
    directories and DIRECTORY/factory.toml. Serves until Ctrl-C."""
    from cellctl.cell.config import load_cell
    from cellctl.factory.emulated import EmulatedFactory
    from cellctl.ui.emulate_cli import refuse_if_running_in

    cells = count if count is not None else len(templates) or 3
    if len(templates) > cells:
        raise click.UsageError(f"{len(templates)} --template for {cells} cells (--cells)")
    # One running in DIRECTORY: refused before its broker's files or cells are rewritten.
    refuse_if_running_in(directory)

    async def main() -> None:
        plant = EmulatedFactory(
            Path(directory),
            cells=cells,
            time_scale=time_scale,
            accept_timeout=accept_timeout,
            templates=[Path(t) for t in templates],
        )
        await plant.start()
        try:
            console.print(
                f"emulated factory: {cells} cells (time scale {time_scale:g}), "
                f"Mosquitto on {plant.broker.url} (its files in {plant.broker.directory})",
                markup=False,
                soft_wrap=True,
            )
            for cell_dir, template in zip(plant.cell_dirs, plant.templates, strict=True):
                what = f"  (emulates {template})" if template is not None else ""
                console.print(
                    f"  cellctl --cell {cell_dir} run{what}", markup=False, soft_wrap=True
                )
            console.print(f"  cellctl factory --dir {directory} run", markup=False, soft_wrap=True)
            # One order for each cell's first part type (each template has its own).
            firsts = dict.fromkeys(t for d in plant.cell_dirs for t in list(load_cell(d).parts)[:1])
            for part_type in firsts:
                console.print(
                    f"  cellctl factory --dir {directory} submit {part_type} --qty 2",
                    markup=False,
                    soft_wrap=True,
                )
            console.print("serving until Ctrl-C", markup=False)
            console.file.flush()  # a pipe or a log file has them now, not at Ctrl-C
            with contextlib.suppress(asyncio.CancelledError):
                await until_stopped()
        finally:
            await plant.close()
            console.print("emulated factory stopped")

    run(main)


factory.add_command(factory_plan)
