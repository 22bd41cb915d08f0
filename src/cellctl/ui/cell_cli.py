"""``cellctl cell check``, ``cellctl run``, ``cellctl emulate cell`` and ``cellctl demo``."""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import click

from cellctl.emulators.cellpanel import HAND_COMMANDS
from cellctl.emulators.serve import CELL_TIME_SCALE, TIME_SCALE_HELP
from cellctl.emulators.switches import check_fault
from cellctl.errors import CellctlError
from cellctl.ui.common import (
    cell_dir,
    console,
    err_console,
    run,
    stdin_lines,
    stop_signals,
    until_stopped,
)
from cellctl.ui.emulate_cli import TIME_SCALE

if TYPE_CHECKING:
    from cellctl.cell.config import CellConfig
    from cellctl.cell.controller import CellController, ControllerOptions, Event
    from cellctl.cell.journal import Journal
    from cellctl.emulators.cell import EmulatedCell
    from cellctl.factory.opcua import OpcuaServer
    from cellctl.mailbox import Mailbox
    from cellctl.mailbox.mqtt import MqttBridge
    from cellctl.service.methods import Dispatcher

# The controller, the API server and the broker client are imported where the cell runs:
# `cellctl cell check` and every `--help` load none of them (tests/test_cli_startup.py).


@click.group("cell")
def cell_group() -> None:
    """The cell as a whole: its cell.toml."""


@cell_group.command("check")
@click.pass_context
def check(ctx: click.Context) -> None:
    """Check cell.toml and every program it names; print every problem."""
    from cellctl.cell.config import check_cell

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


async def run_controller(
    directory: Path,
    *,
    live: bool,
    until_idle: bool,
    options: ControllerOptions | None = None,
    stop: asyncio.Event | None = None,
) -> CellController:
    """Connect and run the controller of ``directory`` until stopped (or idle)."""
    from cellctl.cell.configproblems import require_cell_file
    from cellctl.cell.owner import acquire_controller_lock, refuse_shared_directory

    require_cell_file(directory)  # no cell here: refused before the lock makes state/
    # Before anything is made there: a directory others can write gives the token away.
    refuse_shared_directory(directory)
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
    from rich.live import Live

    from cellctl.cell.config import load_cell
    from cellctl.cell.controller import CellController
    from cellctl.cell.journal import open_journal
    from cellctl.cell.owner import refuse_if_machines_held
    from cellctl.mailbox import open_mailbox
    from cellctl.service.access import AttachedCell
    from cellctl.service.audit import interrupted_note, mark_interrupted
    from cellctl.service.server import ApiServer, api_limits
    from cellctl.service.token import ensure_default
    from cellctl.ui.dashboard.routes import dashboard_routes
    from cellctl.ui.live_view import LiveView

    config = load_cell(directory)
    # The cell's own files first (a token replaced by a link, or too short, is the engineer's
    # to mend, whoever holds a machine); the API server reads the same token again.
    ensure_default(directory)
    # A link held elsewhere (a console standalone): refused now, before the API is served
    # and the journal opened, not once connecting finds it.
    refuse_if_machines_held(config)
    journal = open_journal(directory)
    # Calls the audit trail says are running were cut by the end of the process serving
    # them (a crash, a kill): only the cell's owner, as it starts, may say so.
    cut_short = mark_interrupted(directory)
    mailbox = open_mailbox(directory)
    stop = stop or asyncio.Event()
    console.on_broken_pipe = _output_gone  # type: ignore[method-assign]
    printer = None if live else _print_event
    controller = CellController(config, journal, mailbox, options=options, on_event=printer)
    for entry in cut_short:
        controller.log(interrupted_note(entry))
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
    bridge = _mqtt_bridge(config, controller, mailbox, journal, server.dispatcher)
    if bridge is not None:
        bridge.drop_expired()  # before the controller can start a part of such an order
    bridge_task = None
    opcua = _opcua_server(config, controller)
    # Ctrl-C, SIGTERM: ours from here, as found again once the finally below begins.
    signals = contextlib.ExitStack()
    signals.enter_context(stop_signals(on_signal))
    try:
        # OPC UA first: building its address space holds the loop for seconds on a loaded
        # box, and an API already listening would not answer meanwhile (a client that sees
        # api.sock may connect at once).
        if opcua is not None:
            await opcua.start()
            controller.log(opcua.describe())
        await server.start()
        controller.log(f"control API on {server.where}")
        await controller.connect()
        if bridge is not None:
            bridge_task = asyncio.create_task(bridge.run())
            bridge_task.add_done_callback(lambda t: _bridge_ended(t, controller))
        if live:
            view = LiveView(controller, directory)
            with Live(view.render(console), console=console, refresh_per_second=4) as screen:
                task = asyncio.create_task(controller.run(stop, until_idle=until_idle))
                while not task.done():
                    screen.update(view.render(console))
                    await asyncio.wait({task}, timeout=0.25)
                screen.update(view.render(console))
                await task
        else:
            await controller.run(stop, until_idle=until_idle)
    finally:
        signals.close()
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
    from cellctl.service.access import AttachedCell

    return OpcuaServer(AttachedCell(controller), config.opcua, name=config.name, log=controller.log)


def _mqtt_bridge(
    config: CellConfig,
    controller: CellController,
    mailbox: Mailbox,
    journal: Journal,
    api: Dispatcher,
) -> MqttBridge | None:
    """The MQTT side of the mailbox when ``[mailbox] url`` names a broker; the factory's
    cancels go through ``api`` (the control API's ``orders.cancel``)."""
    from cellctl.factory.cancel import cell_canceller
    from cellctl.mailbox.mqtt import MqttBridge, MqttSettings

    box = config.mailbox
    if box is None or box.url is None or box.credentials is None:
        return None
    ca = config.directory / box.ca if box.ca else None
    settings = MqttSettings.load(box.url, config.directory / box.credentials, ca)
    cancel = cell_canceller(api)
    if box.plan_period is None:
        return MqttBridge(settings, controller, mailbox, journal, log=controller.log, cancel=cancel)
    from cellctl.service.planning import own_plan

    horizon = box.plan_horizon
    return MqttBridge(
        settings,
        controller,
        mailbox,
        journal,
        log=controller.log,
        planner=lambda: own_plan(config.directory, mailbox, journal, horizon),
        plan_period=box.plan_period,
        cancel=cancel,
    )


def _bridge_ended(task: asyncio.Task[None], controller: CellController) -> None:
    """Say so when the MQTT side of the mailbox ends on an error it could not handle."""
    if task.cancelled() or task.exception() is None:
        return
    controller.log(
        f"mailbox: the broker link stopped on an error: {task.exception()!r}; orders from the "
        "broker wait until `cellctl run` is started again"
    )


def _print_event(e: Event) -> None:
    """One event a line, at once (also when the output is a file or a pipe). A pipe whose
    reader is gone (`cellctl run | tee`, and Ctrl-C took tee first) ends the printing, not
    the controller: the journal keeps every event, and the stop goes on as asked."""
    try:
        console.print(_event_line(e), markup=False, soft_wrap=True)
        console.file.flush()
    except BrokenPipeError:
        _output_gone()


def _output_gone() -> None:
    """Standard output is a pipe nobody reads any more: it goes to /dev/null from here (a
    write, or the flush at exit, would fail again). Rich's own answer would end the program
    (SystemExit 1): ``cellctl run`` puts this one in its place."""
    console.quiet = True
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    finally:
        os.close(devnull)


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


def emulate_cell_command() -> click.Command:
    """``cellctl emulate cell`` (made when used: its help names every kind's faults)."""
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
        panel: bool,
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
            # Every switch is checked before a file is written or a machine served: a typo
            # must not leave a cell.toml pointing at a pty that is gone.
            tables = fault_tables(cell)
            for text in fault:
                check_fault(text, tables)
            toml = await cell.start(directory)
            switched = [apply_fault(cell, text, at_start=True) for text in fault]
            console.print(f"emulated cell (time scale {time_scale:g}) wrote {toml}")
            for name, server in cell.servers.items():
                console.print(f"  {name:6s} {server.url}")
            console.print(f"  plc    {cell.plc_url}")
            backend = cell.plc.backend_url
            console.print(f"         behind it, pymodbus on {backend} (no fault switch acts there)")
            for said in switched:  # a default taken is said: "cnc1: drop on (5 lines, its default)"
                console.print(f"  fault {said}", markup=False)
            hands = asyncio.ensure_future(_hand_commands(cell)) if panel else None
            try:
                await until_stopped()
            finally:
                if hands is not None:
                    hands.cancel()
                await cell.close()
                console.print("emulated cell stopped")

        run(main)

    return click.Command(
        "cell",
        callback=callback,
        params=[
            click.Option(
                ["--time-scale"],
                type=TIME_SCALE,
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
            click.Option(
                ["--panel"],
                is_flag=True,
                help="Play the machines' operators by hand: hand commands from stdin, one a "
                f"line: {HAND_COMMANDS}.",
            ),
        ],
        help="Start the robot, both mills and the PLC, and write cell.toml pointing at them."
        + "\n\nFaults (--fault MACHINE:NAME[=ARG], MACHINE a machine of cell.toml or plc), "
        + "by the machine's kind: "
        + kind_faults
        + "; plc: "
        + ", ".join(PLC_FAULTS)
        + ". A mill's stall given here stalls its first cut (its setup block would take it "
        + "otherwise). `cellctl emulate robot|mill|plc --help` says what each does.",
    )


async def _hand_commands(cell: object) -> None:
    """``emulate cell --panel``: hand commands from stdin, one a line, each answered on a
    line (:mod:`cellctl.emulators.cellpanel`), until stdin ends (the cell serves on)."""
    from cellctl.emulators.cellpanel import hand_command

    lines = stdin_lines()
    console.print(f"hand commands (one a line): {HAND_COMMANDS}", markup=False)
    while text := await lines.get():
        try:
            said = await hand_command(cell, text)
        except CellctlError as e:  # a command refused, or a machine that failed it
            said = f"panel: {e}"
        if said:
            console.print(said, markup=False, soft_wrap=True)
            console.file.flush()


def fault_tables(cell: EmulatedCell) -> dict[str, Mapping[str, str]]:
    """Each machine of an emulated cell (started or not) and its fault switches: the robot
    (also as ``robot``), the mills, ``plc``; what :func:`check_fault` checks against."""
    return cell.fault_tables()


def apply_fault(cell: object, text: str, *, at_start: bool = False) -> str:
    """Switch a fault on one machine of an emulated cell: ``cnc1:stall``, ``robot:drop``;
    returns what was switched on, a default taken said (the panel's ``fault``, one code:
    :func:`cellctl.emulators.cellpanel.switch_on`).

    ``at_start``: given as the cell starts (``cellctl emulate cell --fault``). A mill's fault
    that acts as a block ends (``stall``: :data:`~cellctl.emulators.cell.CUT_FAULTS`) is then
    switched on as the mill's first cut starts, as a stall in the middle of a cut comes:
    switched on at once, it would take the setup block, the first block the mill runs."""
    from cellctl.emulators.cellpanel import switch_on

    return switch_on(cell, text, at_start=at_start)
