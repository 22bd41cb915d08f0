"""The running cell's operator commands: ``pause``, ``resume``, ``estop``, ``machine NAME out``
/ ``in`` and ``traffic NAME``. They act through the API of the controller that ``cellctl run``
started (refused, with a reason, when none runs)."""

from __future__ import annotations

import datetime as dt

import click

from cellctl.ui.calls import cell_call
from cellctl.ui.common import console


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


@click.command()
@click.argument("name")
@click.option("--limit", type=click.IntRange(1, 2000), default=40, show_default=True)
@click.pass_context
def traffic(ctx: click.Context, name: str, limit: int) -> None:
    """The last bytes on machine NAME's link, both ways (>> sent, << received)."""
    rows = cell_call(ctx, "traffic.tail", {"machine": name, "limit": limit})
    if not rows:
        console.print(f"no traffic on {name} yet")
    for row in rows:
        stamp = dt.datetime.fromtimestamp(row["time"]).strftime("%H:%M:%S.%f")[:-3]
        console.print(f"{stamp} {row['dir']} {row['hex']:<48} |{row['text']}|", markup=False)
