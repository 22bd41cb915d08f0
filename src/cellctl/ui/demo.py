"""``cellctl demo``: an emulated cell (or a factory of them) runs a mixed batch, and the
figures and Gantt charts say how it went::

    cellctl demo                  # the batch in parallel, then one part at a time, compared
    cellctl demo --dashboard      # the live dashboard; the cell stays up after the batch

Both runs' charts share one time axis (``<out>/gantt.svg`` holds both).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shlex
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from cellctl.clock import current_clock
from cellctl.emulators.serve import DEMO_TIME_SCALE, TIME_SCALE_HELP
from cellctl.errors import UsageError
from cellctl.mailbox.base import MAX_QTY
from cellctl.ui.common import cell_dir, cell_given, console, run
from cellctl.ui.emulate_cli import TIME_SCALE, refuse_if_running_in

if TYPE_CHECKING:
    from cellctl.cell.journal import Journal
    from cellctl.cell.report import Summary
    from cellctl.mailbox import Mailbox

# The controller, the journal and the charts are imported where the batch runs: `cellctl
# demo --help` loads none of them.


@click.command("demo")
@click.option(
    "--time-scale",
    type=TIME_SCALE,
    default=DEMO_TIME_SCALE,
    show_default=True,
    help="Machine time runs this many times faster than real. " + TIME_SCALE_HELP,
)
@click.option(
    "--parts",
    "count",
    type=click.IntRange(min=1, max=MAX_QTY),  # a batch is orders: none past an order's most
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
@click.option(
    "--template",
    "templates",
    multiple=True,
    type=click.Path(file_okay=False, exists=True),
    metavar="DIR",
    help="With --factory: a cell directory to emulate, once per cell (cell1 the first "
    "given...; the rest the example cell); the batch mixes every type the cells make.",
)
@click.pass_context
def demo(
    ctx: click.Context,
    time_scale: float,
    count: int | None,
    out: str,
    compare: bool,
    dashboard: bool,
    cells: int | None,
    templates: tuple[str, ...],
) -> None:
    """Start an emulated cell (or a factory of them), run a mixed batch through it, and
    summarize (under 2 minutes). With --cell DIR, the cell emulated is DIR's (its machines,
    programs and part types) instead of the example cell."""
    template = cell_dir(ctx) if cell_given(ctx) else None
    if template is not None and cells is not None:
        raise click.UsageError("--cell is for one cell, not with --factory")
    if cells is not None and dashboard:
        raise click.UsageError("--dashboard is for one cell, not with --factory")
    if templates and cells is None:
        raise click.UsageError("--template is for --factory N (one cell's is --cell DIR)")
    # A directory that cannot be made or written: refused before the demo runs (making one
    # that is there touches nothing of a demo running in it).
    check_out(Path(out))
    # A demo (or an emulated factory) running in --out: refused before its files are replaced.
    refuse_if_running_in(out)
    if cells is not None:
        from cellctl.ui.factory_demo import run_factory_demo

        chosen = [Path(t) for t in templates]
        raise SystemExit(run(lambda: run_factory_demo(cells, count, time_scale, Path(out), chosen)))
    parts = 6 if count is None else count
    run(lambda: _demo(time_scale, parts, Path(out), compare, dashboard, template))


def check_out(out: Path) -> None:
    """Make the demo's ``--out`` (the factory demo's too), or refuse it in words before the
    demo runs: a directory that cannot be made there, or one it cannot write in."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        why = e.strerror or e
        raise UsageError(f"{out}: cannot write the demo's output there: {why}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise UsageError(f"{out}: cannot write the demo's output there: not writable")


#: The two runs of the demo, as their charts and summaries name them.
PARALLEL = "parts in parallel (cellctl's scheduler)"
ONE_AT_A_TIME = "one part at a time (the source's way)"


async def run_batch(
    directory: Path,
    time_scale: float,
    batch: list[tuple[str, int]],
    *,
    one_at_a_time: bool,
    live: bool,
    dashboard: bool = False,
    template: Path | None = None,
) -> Summary:
    """Emulate the cell in ``directory``, run ``batch`` [(part type, qty)], return figures.

    ``dashboard``: serve the dashboard (URL printed), and after the batch print the figures and
    keep the cell and its controller (the same one, on the same API) up until Ctrl-C."""
    from cellctl.cell.config import load_cell
    from cellctl.cell.controller import ControllerOptions
    from cellctl.cell.report import summarize, write_gantt
    from cellctl.emulators.cell import EmulatedCell, check_cell_dir
    from cellctl.mailbox import open_mailbox
    from cellctl.ui.cell_cli import run_controller
    from cellctl.ui.dashboard.command import serve_dashboard_in

    check_cell_dir(directory)  # a real cell there is refused before anything is removed
    shutil.rmtree(directory, ignore_errors=True)
    cell = EmulatedCell(time_scale=time_scale, template=template)
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
        started = current_clock().now()
        title = ONE_AT_A_TIME if one_at_a_time else PARALLEL
        options = ControllerOptions.from_config(load_cell(directory), one_at_a_time=one_at_a_time)
        config = load_cell(directory)
        machines = [config.robot.name, *(m.name for m in config.mills)]

        def figures(journal: Journal) -> Summary:
            summary = summarize(journal, machines, since=started)
            write_gantt(
                journal,
                machines,
                directory / "gantt.svg",
                since=started,
                title=f"{title}: makespan {summary.makespan_s:.1f} s (time scale {time_scale:g})",
            )
            twice = {
                p: r for p, r in cell.runs_per_part().items() if any(n > 1 for n in r.values())
            }
            summary.extra["parts_cut_twice"] = len(twice)
            return summary

        if not url:
            controller = await run_controller(
                directory, live=live, until_idle=True, options=options, stop=stop
            )
            if stop.is_set():  # Ctrl-C or SIGTERM before the batch was done: no figures
                raise KeyboardInterrupt
            return figures(controller.journal)
        # With the dashboard: one controller for the batch and after it (a second one would
        # start the API and connect to every machine again, and say so).
        done = asyncio.create_task(_after_the_batch(directory, stop, figures, title, url))
        try:
            controller = await run_controller(
                directory, live=False, until_idle=False, options=options, stop=stop
            )
        finally:
            done.cancel()
        return figures(controller.journal)
    finally:
        await cell.close()


async def _after_the_batch(
    directory: Path, stop: asyncio.Event, figures: Any, title: str, url: str
) -> None:
    """Once the batch is done (every order closed or waiting for the operator), print its
    figures and how to go on, while the controller keeps running."""
    from cellctl.cell.journal import open_journal
    from cellctl.mailbox import open_mailbox

    with open_journal(directory) as journal, open_mailbox(directory) as mailbox:
        while not stop.is_set() and not _batch_done(journal, mailbox):
            with contextlib.suppress(TimeoutError):
                async with current_clock().timeout(0.25):
                    await stop.wait()
        if stop.is_set():
            return
        summary = figures(journal)
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


def _batch_done(journal: Journal, mailbox: Mailbox) -> bool:
    """No order open, or every open one waits for the operator (its parts all held): the
    controller's own rule for "idle"."""
    for order in mailbox.orders(states=["posted", "accepted", "in-progress"]):
        parts = journal.parts(order_id=order.id)
        if not parts or any(p.status in ("waiting", "active") for p in parts):
            return False
    return True


async def _demo(
    time_scale: float,
    count: int,
    out: Path,
    compare: bool,
    dashboard: bool = False,
    template: Path | None = None,
) -> None:
    from cellctl.cell.config import load_cell

    half = max(1, count // 2)
    first, second = "wax-robot-base", "wax-toy-mill-table"
    if template is not None:
        types = [*load_cell(template).parts]
        first, second = types[0], types[1 % len(types)]
    batch = [(first, half), (second, count - half)]
    batch = [(part, qty) for part, qty in batch if qty > 0]  # --parts 1: no order for 0
    where = f"{template}'s cell" if template else "an emulated cell (robot, 2 mills, PLC)"
    console.print(
        f"[bold]cellctl demo[/bold]: {where} at time scale "
        f"{time_scale:g}; batch: {' + '.join(f'{qty} {part}' for part, qty in batch)}"
    )
    if dashboard:
        await run_batch(
            out / "cell",
            time_scale,
            batch,
            one_at_a_time=False,
            live=False,
            dashboard=True,
            template=template,
        )
        return
    # A live view on a terminal; elsewhere (a file, a pipe) every event a line as it happens.
    live = console.is_terminal
    summary = await run_batch(
        out / "cell", time_scale, batch, one_at_a_time=False, live=live, template=template
    )
    console.print()
    console.print("\n".join(summary.lines(f"[bold]{PARALLEL}[/bold]")))
    console.print(f"Gantt chart: {out / 'cell' / 'gantt.svg'}")
    if not compare:
        with contextlib.suppress(OSError):
            shutil.copy(out / "cell" / "gantt.svg", out / "gantt.svg")
        return
    console.print("\nthe source's way: one part through its whole route before the next ...")
    base = await run_batch(
        out / "one-at-a-time",
        time_scale,
        batch,
        one_at_a_time=True,
        live=False,
        template=template,
    )
    console.print()
    console.print("\n".join(base.lines(f"[bold]{ONE_AT_A_TIME}[/bold]")))
    console.print(f"Gantt chart: {out / 'one-at-a-time' / 'gantt.svg'}")
    if summary.makespan_s > 0:
        console.print(
            f"\nspeed-up over one part at a time: "
            f"{base.makespan_s / summary.makespan_s:.2f}x "
            f"(machine time x{time_scale:g}: {summary.makespan_s * time_scale / 60:.0f} min "
            f"vs {base.makespan_s * time_scale / 60:.0f} min in the real cell)"
        )
    both = compare_charts(
        [(PARALLEL, out / "cell", summary), (ONE_AT_A_TIME, out / "one-at-a-time", base)],
        time_scale,
        out / "gantt.svg",
    )
    console.print(f"both runs on one time axis: {both}")


def compare_charts(runs: list[tuple[str, Path, Summary]], time_scale: float, path: Path) -> Path:
    """Each run's chart again on one time axis (the longest run's), and all of them in one
    chart at ``path``: the runs compare at a glance."""
    from cellctl.cell.config import load_cell
    from cellctl.cell.journal import open_journal
    from cellctl.cell.report import GanttRun, gantt_runs_svg

    machines: list[str] = []
    charted: list[GanttRun] = []
    for title, directory, summary in runs:
        config = load_cell(directory)
        names = [config.robot.name, *(m.name for m in config.mills)]
        machines += [n for n in names if n not in machines]
        with open_journal(directory) as journal:
            types = {p.id: p.part_type for p in journal.parts()}
            steps = [s for s in journal.steps() if s.started >= summary.started]
        label = f"{title}: makespan {summary.makespan_s:.1f} s (time scale {time_scale:g})"
        charted.append(GanttRun(label, steps, types, summary.started))
    span = max(s.ended - r.start for r in charted for s in r.steps if s.ended is not None)
    for one, (_, directory, _) in zip(charted, runs, strict=True):
        (directory / "gantt.svg").write_text(
            gantt_runs_svg([one], machines, span=span), encoding="utf-8"
        )
    path.write_text(gantt_runs_svg(charted, machines, span=span), encoding="utf-8")
    return path
