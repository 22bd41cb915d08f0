"""Orders, reports, alarms and held parts, from the shell: the system level's and the operator's
side of the cell controller.

``cellctl submit PART [--qty N] [--priority P] [--id ID]`` posts an order; ``cellctl orders``
and ``cellctl reports [--follow]`` show what the cell did with it. ``cellctl alarm clear ID``,
``cellctl part release ID [--redo] [--at LOCATION]`` and ``cellctl part scrap ID`` are the
operator's answers. They write the cell directory's mailbox and journal directly, whether the
controller runs or not: a running controller sees them on its next poll. Each operator
action also posts a report.
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Callable, Sequence
from datetime import datetime
from pathlib import Path
from typing import TypeVar

import click
from rich.table import Table

from cellctl.cell.journal import JOURNAL_FILE, LOCATIONS, PART_STATUSES, Journal, open_journal
from cellctl.errors import UsageError
from cellctl.mailbox import MAILBOX_FILE, ORDER_STATES, Report, open_mailbox
from cellctl.service.machines import load_cell_file
from cellctl.ui.common import cell_dir, console, err_console, run

T = TypeVar("T")

#: Seconds between two looks at the mailbox for ``reports --follow``.
FOLLOW_POLL = 0.5

STATE_STYLE = {
    "held": "yellow",
    "failed": "red",
    "scrapped": "red",
    "cancelled": "dim",
    "done": "green",
    "active": "cyan",
    "in-progress": "cyan",
}


def _run(action: Callable[[], T]) -> T:
    """Run a synchronous command body with the CLI's one-line errors and exit codes."""

    async def main() -> T:
        return action()

    return run(main)


def _when(t: float | None) -> str:
    return "" if t is None else datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S")


def _styled(state: str) -> str:
    style = STATE_STYLE.get(state)
    return f"[{style}]{state}[/{style}]" if style else state


def _journal(directory: Path) -> Journal:
    """The cell's journal, for an operator action: refuses a cell that never ran."""
    if not (directory / JOURNAL_FILE).exists():
        raise UsageError(f"no journal in {directory}: the cell has not run yet")
    return open_journal(directory)


def check_part_type(directory: Path, part_type: str) -> None:
    """Refuse a part type the cell's ``cell.toml`` does not define; warn if there is none."""
    if not (directory / "cell.toml").exists():
        err_console.print(
            f"[yellow]warning:[/yellow] no {directory / 'cell.toml'}: "
            f"part type {part_type!r} not checked"
        )
        return
    parts = load_cell_file(directory).get("parts", {})
    if part_type not in parts:
        known = ", ".join(sorted(parts)) or "none"
        raise UsageError(f"unknown part type {part_type!r} (known in cell.toml: {known})")


# -- orders and reports --------------------------------------------------------------------------


@click.command()
@click.argument("part_type", metavar="PART")
@click.option("--qty", type=click.IntRange(min=1), default=1, show_default=True)
@click.option("--priority", type=int, default=0, show_default=True, help="Higher runs first.")
@click.option(
    "--id",
    "order_id",
    metavar="ID",
    help="The order's id; posting the same id again changes nothing. Default: a new id.",
)
@click.pass_context
def submit(
    ctx: click.Context, part_type: str, qty: int, priority: int, order_id: str | None
) -> None:
    """Post an order for QTY parts of type PART, as the system level would."""
    directory = cell_dir(ctx)

    def action() -> None:
        check_part_type(directory, part_type)
        with open_mailbox(directory) as mailbox:
            order, new = mailbox.post_order(part_type, qty, priority, order_id)
        if new:
            console.print(
                f"order {order.id} posted: {order.qty} × {order.part_type}, "
                f"priority {order.priority}"
            )
        else:
            console.print(f"order {order.id} was posted before ({order.state}): nothing changed")

    _run(action)


@click.command()
@click.option(
    "--state",
    "states",
    multiple=True,
    type=click.Choice(ORDER_STATES),
    help="Only orders in this state (repeatable).",
)
@click.pass_context
def orders(ctx: click.Context, states: Sequence[str]) -> None:
    """List orders and their state, highest priority first, then oldest."""
    directory = cell_dir(ctx)

    def action() -> None:
        if not (directory / MAILBOX_FILE).exists():
            console.print(f"no orders (no mailbox in {directory})")
            return
        with open_mailbox(directory) as mailbox:
            found = mailbox.orders(states or None)
        progress: dict[str, Counter[str]] = {}
        if (directory / JOURNAL_FILE).exists():
            with open_journal(directory) as journal:
                for part in journal.parts():
                    progress.setdefault(part.order_id, Counter())[part.status] += 1
        if not found:
            console.print("no orders")
            return
        table = Table(title="Orders")
        for column in ("Order", "Part", "Qty", "Priority", "State", "Parts", "Posted", "Note"):
            table.add_column(column, justify="right" if column in ("Qty", "Priority") else "left")
        for o in found:
            counts = progress.get(o.id, Counter())
            parts = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
            table.add_row(
                o.id,
                o.part_type,
                str(o.qty),
                str(o.priority),
                _styled(o.state),
                parts,
                _when(o.created),
                o.note,
            )
        console.print(table)

    _run(action)


def _report_row(r: Report) -> tuple[str, ...]:
    return (str(r.seq), _when(r.time), r.kind, r.order_id or "", r.part_id or "", r.text)


@click.command()
@click.option("--since", type=int, default=0, metavar="SEQ", help="Only reports after SEQ.")
@click.option("--limit", type=click.IntRange(min=1), help="At most this many.")
@click.option("--follow", "-f", is_flag=True, help="Keep printing new reports until Ctrl-C.")
@click.pass_context
def reports(ctx: click.Context, since: int, limit: int | None, follow: bool) -> None:
    """List the reports the cell posted (order accepted, steps, alarms, parts, order done)."""
    directory = cell_dir(ctx)
    columns = ("Seq", "Time", "Kind", "Order", "Part", "Text")

    if follow:

        async def follow_reports() -> None:
            seen = since
            with open_mailbox(directory) as mailbox:
                while True:
                    for r in mailbox.reports(seen):
                        console.print("  ".join(x for x in _report_row(r) if x))
                        seen = r.seq
                    await asyncio.sleep(FOLLOW_POLL)

        run(follow_reports)
        return

    def action() -> None:
        if not (directory / MAILBOX_FILE).exists():
            console.print(f"no reports (no mailbox in {directory})")
            return
        with open_mailbox(directory) as mailbox:
            found = mailbox.reports(since, limit)
        if not found:
            console.print("no reports")
            return
        table = Table(title="Reports")
        for column in columns:
            table.add_column(column, justify="right" if column == "Seq" else "left")
        for r in found:
            table.add_row(*_report_row(r))
        console.print(table)

    _run(action)


# -- alarms ---------------------------------------------------------------------------------------


@click.group()
def alarm() -> None:
    """The cell's alarms: list them, clear one."""


@alarm.command("list")
@click.option("--all", "show_all", is_flag=True, help="Cleared alarms too.")
@click.pass_context
def alarm_list(ctx: click.Context, show_all: bool) -> None:
    """List active alarms (all of them with --all)."""
    directory = cell_dir(ctx)

    def action() -> None:
        if not (directory / JOURNAL_FILE).exists():
            console.print("no alarms")
            return
        with open_journal(directory) as journal:
            found = journal.alarms() if show_all else journal.active_alarms()
        if not found:
            console.print("no alarms" if show_all else "no active alarms")
            return
        table = Table(title="Alarms")
        for column in ("Id", "Raised", "Machine", "Code", "Text", "State", "Cleared"):
            table.add_column(column, justify="right" if column == "Id" else "left")
        for a in found:
            state = "[red]active[/red]" if a.state == "active" else a.state
            cleared = f"{_when(a.cleared)} by {a.cleared_by}" if a.cleared else ""
            table.add_row(str(a.id), _when(a.raised), a.machine, a.code, a.text, state, cleared)
        console.print(table)

    _run(action)


@alarm.command("clear")
@click.argument("alarm_id", metavar="ID", type=int)
@click.pass_context
def alarm_clear(ctx: click.Context, alarm_id: int) -> None:
    """Clear alarm ID once its cause is dealt with."""
    directory = cell_dir(ctx)

    def action() -> None:
        with _journal(directory) as journal:
            before = journal.get_alarm(alarm_id)
            if before.state == "cleared":
                console.print(f"alarm {alarm_id} was already cleared")
                return
            a = journal.clear_alarm(alarm_id, by="operator")
        with open_mailbox(directory) as mailbox:
            mailbox.post_report(
                "alarm-cleared",
                f"alarm {a.id} cleared by operator: {a.machine} {a.code} {a.text}",
                data={"alarm": a.id, "machine": a.machine, "code": a.code, "by": "operator"},
            )
        console.print(f"alarm {a.id} cleared ({a.machine} {a.code}: {a.text})")

    _run(action)


# -- parts ----------------------------------------------------------------------------------------


@click.group()
def part() -> None:
    """The cell's parts: list them, release or scrap one held for inspection."""


@part.command("list")
@click.option(
    "--status",
    "statuses",
    multiple=True,
    type=click.Choice(PART_STATUSES),
    help="Only parts with this status (repeatable).",
)
@click.option("--order", "order_id", metavar="ID", help="Only the parts of this order.")
@click.pass_context
def part_list(ctx: click.Context, statuses: Sequence[str], order_id: str | None) -> None:
    """List parts: where each is, how far along its route, and why it is held."""
    directory = cell_dir(ctx)

    def action() -> None:
        if not (directory / JOURNAL_FILE).exists():
            console.print("no parts")
            return
        with open_journal(directory) as journal:
            found = journal.parts(statuses or None, order_id)
        if not found:
            console.print("no parts")
            return
        table = Table(title="Parts")
        for column in ("Part", "Order", "Type", "Location", "Route", "Status", "Note"):
            table.add_column(column, justify="right" if column == "Route" else "left")
        for p in found:
            table.add_row(
                p.id,
                p.order_id,
                p.part_type,
                p.location,
                str(p.route_index),
                _styled(p.status),
                p.note,
            )
        console.print(table)

    _run(action)


@part.command("release")
@click.argument("part_id", metavar="ID")
@click.option("--redo", is_flag=True, help="Run the interrupted step again (default: it is done).")
@click.option(
    "--at",
    "location",
    metavar="LOCATION",
    help=f"Where the part is now ({', '.join(LOCATIONS)}); needed after an interrupted transfer.",
)
@click.pass_context
def part_release(ctx: click.Context, part_id: str, redo: bool, location: str | None) -> None:
    """Release held part ID after inspection: the cell carries on with it."""
    directory = cell_dir(ctx)

    def action() -> None:
        with _journal(directory) as journal:
            p = journal.release_part(part_id, redo_step=redo, location=location)
        what = (
            "its interrupted step will run again" if redo else "its interrupted step counts as done"
        )
        with open_mailbox(directory) as mailbox:
            mailbox.post_report(
                "part-released",
                f"part {p.id} released by operator at {p.location}: {what}",
                order_id=p.order_id,
                part_id=p.id,
                data={"redo": redo, "location": p.location},
            )
        console.print(f"part {p.id} released at {p.location}: {what}")

    _run(action)


@part.command("scrap")
@click.argument("part_id", metavar="ID")
@click.option("--reason", default="scrapped by operator", show_default=True)
@click.pass_context
def part_scrap(ctx: click.Context, part_id: str, reason: str) -> None:
    """Scrap part ID (held or waiting): the cell will not work on it again."""
    directory = cell_dir(ctx)

    def action() -> None:
        with _journal(directory) as journal:
            p = journal.scrap_part(part_id, reason)
        with open_mailbox(directory) as mailbox:
            mailbox.post_report(
                "part-scrapped",
                f"part {p.id} scrapped: {reason}",
                order_id=p.order_id,
                part_id=p.id,
                data={"reason": reason, "location": p.location},
            )
        console.print(f"part {p.id} scrapped")

    _run(action)


__all__ = ["alarm", "check_part_type", "orders", "part", "reports", "submit"]
