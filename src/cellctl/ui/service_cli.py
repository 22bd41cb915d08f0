"""The running cell's operator commands: ``pause``, ``resume``, ``estop``, ``machine NAME out``
/ ``in`` and ``traffic NAME``. They act through the API of the controller that ``cellctl run``
started (refused, with a reason, when none runs).

And ``service install`` / ``service status``: that controller as a systemd service."""

from __future__ import annotations

import datetime as dt
import json
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from cellctl.errors import UsageError
from cellctl.ui.calls import cell_call
from cellctl.ui.common import (
    cell_dir,
    console,
    follow_until_stopped,
    json_option,
    print_json,
    print_line,
    run,
)
from cellctl.ui.systemd_unit import (
    SYSTEM_UNIT_DIR,
    ServiceUnit,
    parse_unit,
    unit_name,
    unit_target,
)


@click.command()
@click.pass_context
def pause(ctx: click.Context) -> None:
    """Let the steps in flight finish and start no new one."""
    console.print(cell_call(ctx, "cell.pause")["message"])


@click.command()
@click.pass_context
def resume(ctx: click.Context) -> None:
    """Start dispatching again after a pause or an emergency stop."""
    console.print(cell_call(ctx, "cell.resume")["message"])


@click.command()
@click.argument("reason", required=False, default="")
@click.pass_context
def estop(ctx: click.Context, reason: str) -> None:
    """Emergency stop: stop the robot, halt the mills, raise an alarm, pause the cell."""
    console.print(cell_call(ctx, "cell.estop", {"reason": reason})["message"])


@click.group()
@click.argument("name")
@click.pass_context
def machine(ctx: click.Context, name: str) -> None:
    """A machine of the running cell: take it out of automatic service, or return it."""
    ctx.obj = {"machine": name}


@machine.command("out")
@click.option("--reason", default="", help="Why (kept in the journal, shown to everyone).")
@click.pass_context
def machine_out(ctx: click.Context, reason: str) -> None:
    """Out of automatic service: no new work; manual functions become possible."""
    name = ctx.obj["machine"]
    params = {"machine": name, "reason": reason}
    console.print(cell_call(ctx, "machines.out_of_service", params)["message"])


@machine.command("in")
@click.pass_context
def machine_in(ctx: click.Context) -> None:
    """Back in automatic service (it is initialized again first if it needs it)."""
    name = ctx.obj["machine"]
    console.print(cell_call(ctx, "machines.return_to_service", {"machine": name})["message"])


#: Seconds between two looks at a machine's traffic for ``traffic --follow``.
TRAFFIC_POLL_S = 0.5


def _traffic_line(row: dict[str, Any]) -> str:
    stamp = dt.datetime.fromtimestamp(row["time"]).strftime("%H:%M:%S.%f")[:-3]
    return f"{stamp} {row['dir']} {row['hex']:<48} |{row['text']}|"


@click.command()
@click.argument("name")
@click.option(
    "--limit",
    type=click.IntRange(1, 2000),
    default=40,
    show_default=True,
    help="How many of the last exchanges to show.",
)
@click.option("--follow", "-f", is_flag=True, help="Keep printing new traffic until Ctrl-C.")
@json_option
@click.pass_context
def traffic(ctx: click.Context, name: str, limit: int, follow: bool, as_json: bool) -> None:
    """The last bytes on machine NAME's link, both ways (>> sent, << received)."""

    def show(row: dict[str, Any]) -> None:
        if as_json:  # one JSON object a line, so that --follow streams
            click.echo(json.dumps(row, ensure_ascii=False))
        else:
            print_line(_traffic_line(row))

    if not follow:
        rows = cell_call(ctx, "traffic.tail", {"machine": name, "limit": limit})
        if as_json:
            print_json(rows)
            return
        if not rows:
            console.print(f"no traffic on {name} yet")
        for row in rows:
            show(row)
        return
    directory = cell_dir(ctx)

    async def follow_traffic() -> None:
        from cellctl.service.client import open_cell

        seen: set[tuple[Any, ...]] = set()
        async with await open_cell(directory, {}) as cell:

            async def step() -> None:
                nonlocal seen
                rows = await cell.call("traffic.tail", {"machine": name, "limit": limit})
                keys = [(row["time"], row["dir"], row["hex"]) for row in rows]
                for key, row in zip(keys, rows, strict=True):
                    if key not in seen:
                        show(row)
                # A row that left the tail cannot come back: remember only the tail, so a
                # follow that runs for a shift keeps a bounded memory.
                seen = set(keys)
                console.file.flush()

            await follow_until_stopped(step, TRAFFIC_POLL_S)

    run(follow_traffic)


# -- the controller as a systemd service ----------------------------------------------------------

#: How long a systemctl query may take.
SYSTEMCTL_TIMEOUT_S = 10.0


def _cell_option(f: Callable[..., None]) -> Callable[..., None]:
    return click.option(
        "--cell",
        "cell",
        type=click.Path(file_okay=False),
        default=None,
        help="The cell directory (default: cellctl's --cell).",
    )(f)


def _unit_cell(ctx: click.Context, cell: str | None) -> Path:
    return (Path(cell) if cell else cell_dir(ctx)).absolute()


@click.group("service")
def service_group() -> None:
    """The cell's controller (`cellctl run`) as a systemd service: install, status."""


@service_group.command("install")
@_cell_option
@click.option("--user", help="Who runs the controller (default: the cell directory's owner).")
@click.option("--name", help="The unit's name (default: cellctl-<cell directory>.service).")
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write the unit here (default, as root: /etc/systemd/system/<name>).",
)
@click.option("--print", "to_stdout", is_flag=True, help="Print the unit instead of writing it.")
@click.option("--force", is_flag=True, help="Replace a unit file that exists.")
@click.pass_context
def service_install(
    ctx: click.Context,
    cell: str | None,
    user: str | None,
    name: str | None,
    output: Path | None,
    to_stdout: bool,
    force: bool,
) -> None:
    """Write the systemd unit that runs this cell's controller.

    It runs `cellctl run` as the cell's user, restarted on failure, with the filesystem
    read-only but for the cell directory and serial ports its only devices. Never replaces a
    unit file without --force."""
    unit = ServiceUnit.for_cell(_unit_cell(ctx, cell), user=user, name=name)
    text = unit.text()
    if to_stdout:
        click.echo(text, nl=False)
        return
    target = unit_target(unit.name, output=output).absolute()
    if target.exists() and not force:
        raise UsageError(f"{target} exists: --force replaces it")
    try:
        target.write_text(text, encoding="utf-8")
    except OSError as e:
        raise UsageError(f"cannot write {target}: {e.strerror or e}") from None
    console.print(
        f"wrote {target}: {unit.name} runs the cell in {unit.cell} as user {unit.user}",
        markup=False,
        soft_wrap=True,
    )
    start = f"systemctl daemon-reload && systemctl enable --now {unit.name}"
    if target.parent != SYSTEM_UNIT_DIR:
        start = f"cp {target} {SYSTEM_UNIT_DIR / unit.name} && {start}"
    console.print(
        f"as root, to start it now and at every boot: {start}", markup=False, soft_wrap=True
    )


@service_group.command("status")
@_cell_option
@click.option("--name", help="The unit's name (default: cellctl-<cell directory>.service).")
@click.option(
    "--unit-file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="The unit file to read (default: /etc/systemd/system/<name>).",
)
@click.pass_context
def service_status(
    ctx: click.Context, cell: str | None, name: str | None, unit_file: Path | None
) -> None:
    """Whether the cell's unit is installed, enabled and active.

    Exit status 1 when it is not installed."""
    directory = _unit_cell(ctx, cell)
    name = name or unit_name(directory)
    path = unit_file or SYSTEM_UNIT_DIR / name
    if not path.is_file():
        console.print(
            f"{name}: not installed (no {path}); `cellctl service install` writes it",
            markup=False,
            soft_wrap=True,
        )
        raise SystemExit(1)
    service = parse_unit(path.read_text(encoding="utf-8")).get("Service", {})
    command = " ".join(service.get("ExecStart", ["?"]))
    user = " ".join(service.get("User", ["root"]))
    rows = [("unit", f"{name}: {path}"), ("runs", f"{command}  (as {user})")]
    words = command.split()
    runs = words[words.index("--cell") + 1] if "--cell" in words[:-1] else ""
    if runs and Path(runs) != directory:
        rows.append(("note", f"it runs the cell in {runs}, not {directory}"))
    rows += _systemd_state(name)
    for key, value in rows:
        console.print(f"{key + ':':9s}{value}", markup=False, soft_wrap=True)


def _systemd_state(name: str) -> list[tuple[str, str]]:
    """Enabled and active, from systemctl; what is missing when systemd does not run here."""
    if shutil.which("systemctl") is None:
        return [("systemd", "not on this machine (no systemctl): nothing starts the unit")]
    if not Path("/run/systemd/system").is_dir():
        return [
            (
                "systemd",
                "not running here (no /run/systemd/system, as in most containers): the unit "
                "cannot be enabled or started on this machine",
            )
        ]
    enabled = _systemctl("is-enabled", name)
    show = _systemctl(
        "show", name, "--property=ActiveState,SubState,ActiveEnterTimestamp,NRestarts,MainPID"
    )
    props = dict(line.partition("=")[::2] for line in show.splitlines())
    active = f"{props.get('ActiveState', '?')} ({props.get('SubState', '?')})"
    if props.get("ActiveState") == "active":
        active += f" since {props.get('ActiveEnterTimestamp', '?')}, pid {props.get('MainPID')}"
    active += f"; restarts {props.get('NRestarts', '?')}"
    return [("enabled", enabled.strip() or "?"), ("active", active)]


def _systemctl(*args: str) -> str:
    try:
        done = subprocess.run(
            ["systemctl", *args], capture_output=True, text=True, timeout=SYSTEMCTL_TIMEOUT_S
        )
    except subprocess.TimeoutExpired:
        return f"systemctl {args[0]} did not answer within {SYSTEMCTL_TIMEOUT_S:g} s"
    return done.stdout or done.stderr
