"""``cellctl cell check``, ``cellctl run``, ``cellctl emulate cell`` and ``cellctl demo``."""

from __future__ import annotations

import asyncio
import contextlib
import shlex
import shutil
import signal
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
from rich.console import Group
from rich.live import Live
from rich.table import Table

from cellctl.cell.config import CellConfig, check_cell, load_cell
from cellctl.cell.controller import CellController, ControllerOptions, Event
from cellctl.cell.journal import Journal, open_journal
from cellctl.cell.owner import acquire_controller_lock
from cellctl.cell.report import Summary, summarize, write_gantt
from cellctl.emulators.serve import CELL_TIME_SCALE, DEMO_TIME_SCALE, TIME_SCALE_HELP, parse_fault
from cellctl.errors import UsageError
from cellctl.mailbox import Mailbox, open_mailbox
from cellctl.mailbox.mqtt import MqttBridge, MqttSettings
from cellctl.service.access import AttachedCell
from cellctl.service.server import ApiServer, api_limits
from cellctl.ui.common import cell_dir, console, err_console, run, until_stopped
from cellctl.ui.dashboard.command import serve_dashboard_in
from cellctl.ui.dashboard.routes import dashboard_routes

if TYPE_CHECKING:
    from cellctl.factory.opcua import OpcuaServer


@click.group("cell")
def cell_group() -> None:
    """The cell as a whole: its cell.toml."""


@cell_group.command("check")
@click.pass_context
def check(ctx: click.Context) -> None:
    """Check cell.toml and every program it names; print every problem."""
    directory = cell_dir(ctx)
    config, problems = check_cell(directory)
    for p in problems:
        console.print(p, markup=False)
    if config is None or problems:
        err_console.print(f"{len(problems)} problem(s) in {directory / 'cell.toml'}")
        raise SystemExit(1)
    mills = ", ".join(m.name for m in config.mills)
    console.print(
        f"{directory / 'cell.toml'}: ok: robot {config.robot.name}, mills {mills}, "
        f"{len(config.robot_programs)} robot programs, part types {', '.join(config.parts)}"
    )


def live_view(controller: CellController) -> Group:
    """The live view: orders, machines and their steps, alarms, recent events."""
    orders = Table(title="orders", expand=True)
    for col in ("order", "part", "qty", "state", "done", "held"):
        orders.add_column(col)
    for o in controller.mailbox.orders()[:12]:
        parts = controller.journal.parts(order_id=o.id)
        done = sum(p.status == "done" for p in parts)
        held = sum(p.status == "held" for p in parts)
        orders.add_row(o.id, o.part_type, str(o.qty), o.state, str(done), str(held))
    machines = Table(title="machines", expand=True)
    for col in ("machine", "state", "current step", "service"):
        machines.add_column(col)
    for view in controller.machines.values():
        service = "in service" if view.in_service else "[red]OUT OF SERVICE[/red]"
        machines.add_row(view.name, view.state, view.step, service)
    alarms = Table(title="active alarms", expand=True)
    for col in ("id", "machine", "alarm"):
        alarms.add_column(col)
    for a in controller.journal.active_alarms()[-6:]:
        alarms.add_row(str(a.id), a.machine, a.text)
    events = Table(title="events", expand=True, show_header=False)
    events.add_column("time", width=10)
    events.add_column("event")
    for e in controller.events[-6:]:
        events.add_row(time.strftime("%H:%M:%S", time.localtime(e.time)), e.text)
    return Group(orders, machines, alarms, events)


async def run_controller(
    directory: Path,
    *,
    live: bool,
    until_idle: bool,
    options: ControllerOptions | None = None,
    stop: asyncio.Event | None = None,
) -> CellController:
    """Connect and run the controller of ``directory`` until stopped (or idle)."""
    # First: a refused controller reads and writes nothing. Held until every link is closed.
    with acquire_controller_lock(directory):
        return await _run_owned(
            directory, live=live, until_idle=until_idle, options=options, stop=stop
        )


async def _run_owned(
    directory: Path,
    *,
    live: bool,
    until_idle: bool,
    options: ControllerOptions | None,
    stop: asyncio.Event | None,
) -> CellController:
    config = load_cell(directory)
    journal = open_journal(directory)
    mailbox = open_mailbox(directory)
    stop = stop or asyncio.Event()
    printer = None if live else _print_event
    controller = CellController(config, journal, mailbox, options=options, on_event=printer)
    loop = asyncio.get_running_loop()
    presses = 0

    def on_signal() -> None:
        nonlocal presses
        presses += 1
        if presses == 1:
            controller.log("stopping: steps in flight finish first (Ctrl-C again to abort)")
            stop.set()
        else:
            raise KeyboardInterrupt

    server = ApiServer(
        AttachedCell(controller),
        directory,
        listen=config.api_listen,
        allow_remote=config.api_allow_remote,
        extra_routes=dashboard_routes,
        limits=api_limits(config.api),
    )
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, on_signal)
    bridge = _mqtt_bridge(config, controller, mailbox, journal)
    if bridge is not None:
        bridge.drop_expired()  # before the controller can start a part of such an order
    bridge_task = None
    opcua = _opcua_server(config, controller)
    try:
        await server.start()
        controller.log(f"control API on {server.url}")
        if opcua is not None:
            await opcua.start()
            controller.log(opcua.describe())
        await controller.connect()
        if bridge is not None:
            bridge_task = asyncio.create_task(bridge.run())
            bridge_task.add_done_callback(lambda t: _bridge_ended(t, controller))
        if live:
            with Live(live_view(controller), console=console, refresh_per_second=4) as screen:
                task = asyncio.create_task(controller.run(stop, until_idle=until_idle))
                while not task.done():
                    screen.update(live_view(controller))
                    await asyncio.wait({task}, timeout=0.25)
                screen.update(live_view(controller))
                await task
        else:
            await controller.run(stop, until_idle=until_idle)
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        if bridge is not None and bridge_task is not None:
            await bridge.stop()  # the last reports and "offline" go out first
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(5):
                    await bridge_task
            bridge_task.cancel()
        if opcua is not None:
            await opcua.close()
        await server.close()
        await controller.close()
    return controller


def _opcua_server(config: CellConfig, controller: CellController) -> OpcuaServer | None:
    """The OPC UA server when ``[opcua] listen`` is set (asyncua is imported only then)."""
    if config.opcua is None or config.opcua.listen is None:
        return None
    from cellctl.factory.opcua import OpcuaServer

    return OpcuaServer(AttachedCell(controller), config.opcua, name=config.name, log=controller.log)


def _mqtt_bridge(
    config: CellConfig, controller: CellController, mailbox: Mailbox, journal: Journal
) -> MqttBridge | None:
    """The MQTT side of the mailbox when ``[mailbox] url`` names a broker."""
    box = config.mailbox
    if box is None or box.url is None or box.credentials is None:
        return None
    ca = config.directory / box.ca if box.ca else None
    settings = MqttSettings.load(box.url, config.directory / box.credentials, ca)
    return MqttBridge(settings, controller, mailbox, journal, log=controller.log)


def _bridge_ended(task: asyncio.Task[None], controller: CellController) -> None:
    """Say so when the MQTT side of the mailbox ends on an error it could not handle."""
    if task.cancelled() or task.exception() is None:
        return
    controller.log(
        f"mailbox: the broker link stopped on an error: {task.exception()!r}; orders from the "
        "broker wait until `cellctl run` is started again"
    )


def _print_event(e: Event) -> None:
    """One event a line, at once (also when the output is a file or a pipe)."""
    console.print(_event_line(e), markup=False, soft_wrap=True)
    console.file.flush()


def _event_line(e: Event) -> str:
    return f"{time.strftime('%H:%M:%S', time.localtime(e.time))} {e.text}"


@click.command("run")
@click.option(
    "--live/--no-live",
    default=None,
    help="Live view, or a plain event log a line at a time (the default when the output is "
    "not a terminal).",
)
@click.option("--until-idle", is_flag=True, help="Return once every order is done or held.")
@click.pass_context
def run_command(ctx: click.Context, live: bool | None, until_idle: bool) -> None:
    """Run the cell controller in the foreground; Ctrl-C stops it cleanly.

    It is the one owner of the cell's machines, and serves the control API on the cell's
    socket (and on [api] listen): `cellctl console` and every other command go through it.
    """
    directory = cell_dir(ctx)
    live_view_on = console.is_terminal if live is None else live
    run(lambda: _run(directory, live_view_on, until_idle))


async def _run(directory: Path, live: bool, until_idle: bool) -> None:
    await run_controller(directory, live=live, until_idle=until_idle)


def _emulate_cell_command() -> click.Command:
    from cellctl.emulators.cell import EmulatedCell
    from cellctl.emulators.plc import FAULTS as PLC_FAULTS
    from cellctl.kinds import registry

    # Each kind's fault switches, as its declaration names them (the 7547 shares the 7545's).
    by_faults: dict[tuple[str, ...], list[str]] = {}
    for kind in registry.kinds():
        if kind.faults:
            by_faults.setdefault(tuple(kind.faults), []).append(kind.name)
    kind_faults = "; ".join(
        f"{', '.join(names)}: {', '.join(faults)}" for faults, names in by_faults.items()
    )

    def callback(
        time_scale: float,
        no_pacing: bool,
        robot_listen: str,
        fault: tuple[str, ...],
        template: str | None,
    ) -> None:
        ctx = click.get_current_context()
        directory = cell_dir(ctx)

        async def main() -> None:
            # The template's machines and kinds are what is served (not the example cell's).
            cell = EmulatedCell(
                time_scale=time_scale,
                pacing=not no_pacing,
                robot_listen=robot_listen,
                template=Path(template) if template else None,
            )
            toml = await cell.start(directory)
            for text in fault:
                apply_fault(cell, text)
            console.print(f"emulated cell (time scale {time_scale:g}) wrote {toml}")
            for name, server in cell.servers.items():
                console.print(f"  {name:6s} {server.url}")
            console.print(f"  plc    {cell.plc_url}")
            backend = cell.plc.backend_url
            console.print(f"         behind it, pymodbus on {backend} (no fault switch acts there)")
            try:
                await until_stopped()
            finally:
                await cell.close()
                console.print("emulated cell stopped")

        run(main)

    return click.Command(
        "cell",
        callback=callback,
        params=[
            click.Option(
                ["--time-scale"],
                type=float,
                default=CELL_TIME_SCALE,
                show_default=True,
                help="Machine time runs this many times faster than real (1: real time). "
                + TIME_SCALE_HELP,
            ),
            click.Option(["--no-pacing"], is_flag=True, help="Move bytes as fast as they come."),
            click.Option(
                ["--robot-listen"],
                default="pty",
                show_default=True,
                help="Where the robot listens: pty, pty:PATH, socket://HOST:PORT or rfc2217://HOST:PORT.",
            ),
            click.Option(
                ["--fault"], multiple=True, metavar="MACHINE:NAME[=ARG]", help="e.g. cnc1:stall"
            ),
            click.Option(
                ["--template"],
                help="Cell directory to copy (default: the example cell shipped with cellctl).",
            ),
        ],
        help="Start the robot, both mills and the PLC, and write cell.toml pointing at them."
        + "\n\nFaults (--fault MACHINE:NAME[=ARG], MACHINE a machine of cell.toml or plc), "
        + "by the machine's kind: "
        + kind_faults
        + "; plc: "
        + ", ".join(PLC_FAULTS)
        + ". `cellctl emulate robot|mill|plc --help` says what each does.",
    )


emulate_cell = _emulate_cell_command()


def apply_fault(cell: object, text: str) -> None:
    """Switch a fault on one machine of an emulated cell: ``cnc1:stall``, ``robot:drop``."""
    machine, sep, rest = text.partition(":")
    if not sep:
        raise UsageError(f"fault {text!r}: write MACHINE:NAME[=ARG], e.g. cnc1:stall")
    name, arg = parse_fault(rest)
    c: Any = cell
    machines = {"robot": c.robot, c.robot_name: c.robot, **c.mills, "plc": c.plc}
    target = machines.get(machine)
    if target is None:
        known = ", ".join(dict.fromkeys([c.robot_name, *c.mills, "plc"]))
        raise UsageError(f"fault {text!r}: no machine {machine!r} ({known})")
    target.set_fault(name, arg)


@click.command("demo")
@click.option(
    "--time-scale",
    type=float,
    default=DEMO_TIME_SCALE,
    show_default=True,
    help="Machine time runs this many times faster than real. " + TIME_SCALE_HELP,
)
@click.option(
    "--parts",
    "count",
    type=click.IntRange(min=1),
    default=None,
    help="Parts in the batch.  [default: 6; with --factory N: 3 per cell]",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False),
    default="demo-out",
    show_default=True,
    help="Directory for the demo's cells, Gantt charts and figures (replaced each run).",
)
@click.option("--compare/--no-compare", default=True, help="Also run one part at a time.")
@click.option(
    "--dashboard",
    is_flag=True,
    help="Serve the web dashboard (its URL is printed) and keep the cell up after the batch "
    "until Ctrl-C.",
)
@click.option(
    "--factory",
    "cells",
    type=click.IntRange(2, 32),
    default=None,
    metavar="N",
    help="Instead: N emulated cells, each run by its own `cellctl run`, and the factory "
    "spreading the batch over them through a private Mosquitto.",
)
def demo(
    time_scale: float,
    count: int | None,
    out: str,
    compare: bool,
    dashboard: bool,
    cells: int | None,
) -> None:
    """Start an emulated cell (or a factory of them), run a mixed batch through it, and
    summarize (under 2 minutes)."""
    if cells is not None and dashboard:
        raise click.UsageError("--dashboard is for one cell, not with --factory")
    Path(out).mkdir(parents=True, exist_ok=True)
    if cells is not None:
        from cellctl.ui.factory_demo import run_factory_demo

        raise SystemExit(run(lambda: run_factory_demo(cells, count, time_scale, Path(out))))
    run(lambda: _demo(time_scale, 6 if count is None else count, Path(out), compare, dashboard))


async def run_batch(
    directory: Path,
    time_scale: float,
    batch: list[tuple[str, int]],
    *,
    one_at_a_time: bool,
    live: bool,
    dashboard: bool = False,
) -> Summary:
    """Emulate the cell in ``directory``, run ``batch`` [(part type, qty)], return figures.

    ``dashboard``: serve the dashboard (URL printed), and after the batch print the figures and
    keep the cell and a controller up until Ctrl-C."""
    from cellctl.emulators.cell import EmulatedCell

    shutil.rmtree(directory, ignore_errors=True)
    cell = EmulatedCell(time_scale=time_scale)
    try:
        await cell.start(directory)
        url = serve_dashboard_in(directory) if dashboard else ""
        if url:
            console.print(f"dashboard: {url}", markup=False, soft_wrap=True)
        stop = asyncio.Event()
        mailbox = open_mailbox(directory)
        for i, (part, qty) in enumerate(batch, start=1):
            mailbox.post_order(part, qty, order_id=f"{'S' if one_at_a_time else 'O'}{i}")
        mailbox.close()
        started = time.time()
        options = ControllerOptions.from_config(load_cell(directory), one_at_a_time=one_at_a_time)
        controller = await run_controller(
            directory, live=live, until_idle=True, options=options, stop=stop
        )
        machines = [controller.config.robot.name, *(m.name for m in controller.config.mills)]
        summary = summarize(controller.journal, machines, since=started)
        title = "one part at a time" if one_at_a_time else "cellctl schedule"
        write_gantt(
            controller.journal,
            machines,
            directory / "gantt.svg",
            since=started,
            title=f"{title}: makespan {summary.makespan_s:.1f} s (time scale {time_scale:g})",
        )
        twice = {p: r for p, r in cell.runs_per_part().items() if any(n > 1 for n in r.values())}
        summary.extra["parts_cut_twice"] = len(twice)
        if url and not stop.is_set():
            console.print()
            console.print("\n".join(summary.lines(f"[bold]{title}[/bold]")))
            console.print(f"\nthe batch is done; the cell and the dashboard stay up: {url}")
            # The exact command, with the absolute directory: it works from any shell.
            where = shlex.quote(str(directory.absolute()))  # noqa: ASYNC240 (no disk I/O)
            console.print(
                "submit orders there, or from another shell with: "
                f"cellctl --cell {where} submit wax-robot-base   (Ctrl-C stops)",
                markup=False,
                soft_wrap=True,
            )
            await run_controller(directory, live=False, until_idle=False, options=options)
        return summary
    finally:
        await cell.close()


async def _demo(
    time_scale: float, count: int, out: Path, compare: bool, dashboard: bool = False
) -> None:
    half = max(1, count // 2)
    batch = [("wax-robot-base", half), ("wax-toy-mill-table", count - half)]
    batch = [(part, qty) for part, qty in batch if qty > 0]  # --parts 1: no order for 0
    console.print(
        f"[bold]cellctl demo[/bold]: an emulated cell (robot, 2 mills, PLC) at time scale "
        f"{time_scale:g}; batch: {half} wax-robot-base + {count - half} wax-toy-mill-table"
    )
    if dashboard:
        await run_batch(
            out / "cell", time_scale, batch, one_at_a_time=False, live=False, dashboard=True
        )
        return
    # A live view on a terminal; elsewhere (a file, a pipe) every event a line as it happens.
    live = console.is_terminal
    summary = await run_batch(out / "cell", time_scale, batch, one_at_a_time=False, live=live)
    console.print()
    console.print("\n".join(summary.lines("[bold]cellctl schedule[/bold]")))
    console.print(f"Gantt chart: {out / 'cell' / 'gantt.svg'}")
    if compare:
        console.print("\nthe source's way: one part through its whole route before the next ...")
        base = await run_batch(
            out / "one-at-a-time", time_scale, batch, one_at_a_time=True, live=False
        )
        console.print()
        console.print("\n".join(base.lines("[bold]one part at a time[/bold]")))
        console.print(f"Gantt chart: {out / 'one-at-a-time' / 'gantt.svg'}")
        if summary.makespan_s > 0:
            console.print(
                f"\nspeed-up over one part at a time: "
                f"{base.makespan_s / summary.makespan_s:.2f}x "
                f"(machine time x{time_scale:g}: {summary.makespan_s * time_scale / 60:.0f} min "
                f"vs {base.makespan_s * time_scale / 60:.0f} min in the real cell)"
            )
    with contextlib.suppress(OSError):
        shutil.copy(out / "cell" / "gantt.svg", out / "gantt.svg")
