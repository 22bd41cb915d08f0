"""``cellctl plan``: what the cell will finish, and when, played ahead on virtual time.

::

    cellctl plan                                        # the running cell, the next 8 h
    cellctl plan --fault cnc2:down@10:00-11:00          # ... if cnc2 is down 10 to 11
    cellctl plan --add wax-robot-base:40 --until 'FRI 18:00'   # can we take 40 more?
    cellctl plan --add 'wax-robot-base:40 by FRI 18:00' --until 'FRI 18:00'  # ... by Friday?
    cellctl plan --dir cell --orders week.csv --policy all --out plan-out
    cellctl plan --replay plan-out/inputs.json          # the same plan again

From the running cell (found as the other commands find it) the plan comes through the
control API's ``plan.run``: the cell's open orders, held parts and machines out of service
now. With ``--dir`` it is played here, from a cell directory and an orders file (docs/plan.md).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from cellctl.clock import current_clock
from cellctl.errors import CellctlError, UsageError
from cellctl.plan.when import MAX_POLL_S, PLAN_POLL_S, parse_poll
from cellctl.ui.common import cell_dir, console, fail, print_json, print_line, run
from cellctl.ui.plan_progress import ProgressLine, progress_line

T = TypeVar("T")


class PollType(click.ParamType[float, Any]):
    """Seconds between a plan's looks, refused in the words of the console and the API
    (:func:`cellctl.plan.when.parse_poll`)."""

    name = "seconds"

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> float:
        try:
            return parse_poll(value)
        except UsageError as e:
            self.fail(str(e), param, ctx)


#: ``--poll`` of ``cellctl plan`` and ``cellctl factory plan`` (unset: the plan's own).
poll_option = click.option(
    "--poll",
    type=PollType(),
    metavar="SECONDS",
    help="How often the planned controller looks at idle machines (the cell's own period "
    "if longer). Looks are most of a plan's work and move its schedule by seconds a "
    f"shift; a fault in the plan is noticed up to this late. More than 0, at most "
    f"{MAX_POLL_S:g}.  [default: {PLAN_POLL_S:g}]",
)


def _check_syntax(
    shift: str | None, until: str | None, adds: tuple[str, ...], faults: Any
) -> float:
    """The options' syntax, before the cell is reached (the cell checks them again, against
    its machines and part types, at its own time); the plan's span, s."""
    from cellctl.plan.spec import parse_add, parse_fault, plan_window

    now = current_clock().now()
    end = plan_window(now, shift, until)
    for text in adds:
        parse_add(text)
    for text in faults:
        parse_fault(text, now, None)
    return end - now


def _local_plan(
    directory: Path,
    orders_file: Path | None,
    start_text: str | None,
    options: dict[str, Any],
    line: ProgressLine | None = None,
) -> Any:
    from cellctl.plan.orders_file import read_orders_file
    from cellctl.plan.run import play_in_temp
    from cellctl.plan.spec import plan_inputs
    from cellctl.plan.when import parse_start
    from cellctl.service.machines import load_cell_file

    if not (directory / "cell.toml").is_file():
        raise UsageError(f"{directory}: no cell.toml: not a cell directory")
    start = parse_start(start_text, current_clock().now())
    orders: tuple[Any, ...] = ()
    if orders_file is not None:
        parts = load_cell_file(directory).get("parts")
        made = list(parts) if isinstance(parts, dict) else None
        orders = read_orders_file(orders_file, start, made)
    if not orders and not options["adds"]:
        if orders_file is not None:
            raise UsageError(
                f"{orders_file}: no orders under its header: add rows, or --add PART:QTY"
            )
        raise UsageError("nothing to plan: give --orders FILE or --add PART:QTY")
    inputs, policies = plan_inputs(directory, start=start, orders=orders, **options)
    told = None if line is None else line.told(inputs.until - inputs.start)
    return play_in_temp(inputs, policies, workers=os.cpu_count() or 1, progress=told)


@click.command("plan")
@click.option(
    "--dir",
    "directory",
    type=click.Path(file_okay=False, path_type=Path),
    help="Plan from this cell directory (cell.toml) instead of the running cell.",
)
@click.option(
    "--orders",
    "orders_file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="With --dir: the orders, CSV (id,part_type,qty,priority,due).",
)
@click.option("--shift", metavar="SPAN", help="How far ahead: 8h, 90m, 2d ...  [default: 8h]")
@click.option("--until", metavar="TIME", help="Or up to: 'FRI 18:00', 18:00, 2026-11-27T18:00.")
@click.option(
    "--start",
    "start_text",
    metavar="TIME",
    help="With --dir: when the plan starts (a time as --until takes).  [default: now]",
)
@click.option(
    "--add",
    "adds",
    multiple=True,
    metavar="PART:QTY[@PRIO][ by WHEN]",
    help="Add an order (repeatable): wax-robot-base:40, :40@5 with a priority, "
    "'wax-robot-base:40@5 by FRI 18:00' due then (WHEN as --until takes it): the plan says "
    "whether it is done by then.",
)
@click.option(
    "--fault",
    "faults",
    multiple=True,
    metavar="MACHINE:FAULT@HH:MM-HH:MM",
    help="A fault window (repeatable): FAULT is down (out of service) or an emulator "
    "fault switch (cnc1:stall@10:00-10:20); each time HH:MM, 'DAY HH:MM' or a date and time "
    "(2026-11-30T06:30); without an end, to the plan's end.",
)
@click.option(
    "--policy",
    default="default",
    show_default=True,
    metavar="NAME",
    help="The scheduler's policy: default (downstream-first), one-at-a-time, shortest-first, "
    "A,B (those compared) or all.",
)
@click.option(
    "--seed",
    type=click.IntRange(0, 2**63 - 1),
    metavar="N",
    default=0,
    show_default=True,
    help="Seed of anything random in the emulated machines.",
)
@poll_option
@click.option(
    "--replay",
    type=click.Path(dir_okay=False, path_type=Path),
    metavar="INPUTS",
    help="Play a saved plan's inputs.json again (the other inputs are its own).",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    help="Write plan.json, plan.svg (the Gantt chart), inputs.json and the cell's "
    "configuration here.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the plan as JSON.")
@click.pass_context
def plan_command(
    ctx: click.Context,
    directory: Path | None,
    orders_file: Path | None,
    shift: str | None,
    until: str | None,
    start_text: str | None,
    adds: tuple[str, ...],
    faults: tuple[str, ...],
    policy: str,
    seed: int,
    poll: float | None,
    replay: Path | None,
    out: Path | None,
    as_json: bool,
) -> None:
    """What the cell finishes, and when: per order against its due time, utilizations, and
    the Gantt chart, played ahead by the real controller on virtual time (in seconds)."""
    from cellctl.plan.run import check_out, result_from_dict, write_plan

    if out is not None:  # before a plan is played, not after
        guarded(lambda: check_out(out))
    options: dict[str, Any] = dict(
        shift=shift, until=until, adds=adds, faults=faults, policy=policy, seed=seed
    )
    if poll is not None:
        options["poll_period"] = poll

    if replay is not None:
        given = [n for n, v in (("--dir", directory), ("--orders", orders_file),
                 ("--shift", shift), ("--until", until), ("--start", start_text),
                 ("--poll", poll)) if v] + (
            ["--add"] * bool(adds) + ["--fault"] * bool(faults)
        )  # fmt: skip
        # Options with defaults: given when typed (the inputs keep their own seed and policies).
        given += [
            f"--{name}"
            for name in ("seed", "policy")
            if ctx.get_parameter_source(name) is not click.core.ParameterSource.DEFAULT
        ]
        if given:
            raise click.UsageError(f"--replay plays its own inputs: not with {', '.join(given)}")
        with progress_line(as_json) as line:
            result = guarded(lambda: _replay(replay, line))
    elif directory is not None:
        with progress_line(as_json) as line:
            result = guarded(lambda: _local_plan(directory, orders_file, start_text, options, line))
    else:
        if orders_file is not None or start_text is not None:
            raise click.UsageError(
                "--orders and --start are for --dir: a plan of the running cell starts now, "
                "from its own orders (add more with --add)"
            )
        span_s = guarded(lambda: _check_syntax(shift, until, adds, faults))
        params: dict[str, Any] = {
            k: v for k, v in dict(shift=shift, until=until, policy=policy).items() if v
        }
        params.update(seed=seed, add=list(adds), fault=list(faults))
        if poll is not None:
            params["poll"] = poll
        with progress_line(as_json) as line:
            answer = _call_plan(ctx, params, span_s, line)
        here = cell_dir(ctx)
        result = guarded(lambda: result_from_dict(answer["plan"], answer["svg"], here))
        result.inputs = dataclasses.replace(result.inputs, cell_dir=here)
    written = guarded(lambda: write_plan(result, out)) if out is not None else []
    if as_json:
        print_json(result.as_dict())
        return
    for line in result.lines():
        print_line(line)
    for path in written:
        console.print(f"saved {path}", markup=False, highlight=False)


def _replay(path: Path, line: ProgressLine | None = None) -> Any:
    from cellctl.plan.inputs import load_inputs
    from cellctl.plan.run import play_in_temp

    inputs, policies = load_inputs(path)
    told = None if line is None else line.told(inputs.until - inputs.start)
    return play_in_temp(inputs, policies, workers=os.cpu_count() or 1, progress=told)


def _call_plan(
    ctx: click.Context, params: dict[str, Any], span_s: float, line: ProgressLine | None
) -> Any:
    """``plan.run`` on the cell (as :func:`~cellctl.ui.calls.cell_call`, waited for as
    :func:`~cellctl.service.client.plan_call` waits), its progress on ``line``."""
    directory = cell_dir(ctx)

    async def main() -> Any:
        # Here, not at the top: `cellctl plan --help` loads no API client.
        from cellctl.service.client import open_cell, plan_call

        async with await open_cell(directory, {}) as cell:
            return await plan_call(cell, params, span_s, None if line is None else line.from_api)

    return run(main)


def guarded(fn: Callable[[], T]) -> T:
    """``fn()``, a typed error turned into one line on stderr and an exit code (a plan plays
    on its own virtual-time loop: not inside :func:`~cellctl.ui.common.run`'s)."""
    try:
        return fn()
    except CellctlError as e:
        fail(e)


__all__ = ["plan_command", "poll_option"]
