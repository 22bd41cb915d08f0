"""Orders, reports, alarms and held parts, from the shell: the system level's and the operator's
side of the cell controller.

``cellctl submit PART [--qty N] [--priority P] [--id ID] [--due WHEN]`` posts an order (due
by ``WHEN``, as ``cellctl plan --until`` takes it, on the cell's clock); ``cellctl orders``
and ``cellctl reports [--follow]`` show what the cell did with it. ``cellctl alarm clear ID``,
``cellctl part release ID [--redo] [--at LOCATION]`` and ``cellctl part scrap ID`` are the
operator's answers. While `cellctl run` runs the cell they go through its control API;
otherwise they write the cell directory's mailbox and journal directly. Either way the same
code (:mod:`cellctl.service.operator`) does the work and posts the report.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any, TypeVar

import click
from rich.table import Table
from rich.text import Text

from cellctl.cell.causes import PRIORITIES
from cellctl.cell.journal import MAX_SHELVE, PART_STATUSES
from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.mailbox import MAILBOX_FILE, ORDER_STATES, Report, open_mailbox
from cellctl.ui.calls import cell_call
from cellctl.ui.common import (
    cell_dir,
    cell_given,
    console,
    err_console,
    follow_until_stopped,
    json_option,
    print_json,
    print_line,
    print_table,
    run,
)

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


def due_cell(due: float | None, late: bool) -> Text:
    """An order's due time as ``cellctl orders`` shows it (``cellctl run``'s live view too):
    ``2026-12-04 18:00:00``, then ``LATE`` in red once the order is late; empty for none."""
    shown = Text(_when(due))
    if late:
        shown.append(" LATE", style="red")
    return shown


def _styled(state: str) -> str:
    style = STATE_STYLE.get(state)
    return f"[{style}]{state}[/{style}]" if style else state


def _controller_runs(directory: Path) -> bool:
    from cellctl.cell.owner import controller_holder

    return controller_holder(directory) is not None


def no_cell_message(directory: Path, named: bool) -> str:
    """Why an order is refused where there is no cell, and how to name one."""
    where = str(directory.absolute())
    if not named:
        where += " (the default: no --cell given, no CELLCTL_CELL)"
    return (
        f"no cell in {where}: no cell.toml, no mailbox, no controller running; name the cell "
        "directory with `cellctl --cell DIR submit ...`, `cellctl submit ... --cell DIR` "
        "or CELLCTL_CELL=DIR (`cellctl --cell DIR emulate cell` or `cellctl demo` makes one)"
    )


# -- orders and reports --------------------------------------------------------------------------


def due_option(clock: str, then: str = "") -> Callable[[Any], Any]:
    """``--due WHEN`` of a command that posts an order, read on ``clock`` (its words);
    ``then`` adds what becomes of it."""
    return click.option(
        "--due",
        metavar="WHEN",
        help=f"When it is due, on {clock}: FRI 18:00 or 18:00 (the next such time), or a date "
        f"and time (2026-12-04T18:00; one already past is taken: the order is late).{then}",
    )


def checked_due(due: str | None, now: float) -> float | None:
    """``--due``'s text as unix seconds (None for none), or UsageError saying why, before
    anything is written or sent."""
    if due is None:
        return None
    from cellctl.service.orderdue import resolve_due

    try:
        return resolve_due(due, now)
    except UsageError as e:
        raise UsageError(f"--due: {e}") from None


@click.command()
@click.argument("part_type", metavar="PART")
@click.option(
    "--qty", type=click.IntRange(min=1), default=1, show_default=True, help="How many parts."
)
@click.option("--priority", type=int, default=0, show_default=True, help="Higher runs first.")
@click.option(
    "--id",
    "order_id",
    metavar="ID",
    help="The order's id; posting the same id again changes nothing. Default: a new id.",
)
@due_option("the cell's clock")
@click.pass_context
def submit(
    ctx: click.Context,
    part_type: str,
    qty: int,
    priority: int,
    order_id: str | None,
    due: str | None,
) -> None:
    """Post an order for QTY parts of type PART, as the system level would."""
    checked_due(due, current_clock().now())  # before a mailbox is opened; the cell reads
    # it again on its own clock
    directory = cell_dir(ctx)

    has_toml = (directory / "cell.toml").exists()
    if not has_toml and not (directory / MAILBOX_FILE).exists() and not _controller_runs(directory):
        # No cell here: posting would make a mailbox no controller reads, and no part.
        raise UsageError(no_cell_message(directory, cell_given(ctx)))
    if not has_toml:
        err_console.print(
            f"[yellow]warning:[/yellow] no {directory / 'cell.toml'}: "
            f"part type {part_type!r} not checked"
        )
    params: dict[str, object] = {"part_type": part_type, "qty": qty, "priority": priority}
    if order_id is not None:
        params["id"] = order_id
    if due is not None:
        params["due"] = due
    console.print(cell_call(ctx, "orders.submit", params)["message"])


@click.command()
@click.option(
    "--state",
    "states",
    multiple=True,
    type=click.Choice(ORDER_STATES),
    help="Only orders in this state (repeatable).",
)
@json_option
@click.pass_context
def orders(ctx: click.Context, states: Sequence[str], as_json: bool) -> None:
    """List orders and their state, highest priority first, then oldest."""
    directory = cell_dir(ctx)

    if not (directory / MAILBOX_FILE).exists() and not _controller_runs(directory):
        from cellctl.service.client import require_cell

        require_cell(directory)  # a mistyped --cell is not an empty cell
        if as_json:
            print_json([])
            return
        console.print(f"no orders (no mailbox in {directory})")
        return
    found = cell_call(ctx, "orders.list", {"states": list(states) or None})
    if as_json:
        print_json(found)
        return
    if not found:
        console.print("no orders")
        return
    table = Table(title="Orders")
    for column in ("Order", "Part", "Qty", "Priority", "State", "Parts", "Posted", "Due", "Note"):
        table.add_column(column, justify="right" if column in ("Qty", "Priority") else "left")
    for o in found:
        parts = ", ".join(f"{n} {s}" for s, n in o["parts"].items())
        # .get: a controller of an older cellctl answers without due times.
        due = due_cell(o.get("due"), bool(o.get("late")))
        table.add_row(
            o["id"],
            o["part_type"],
            str(o["qty"]),
            str(o["priority"]),
            _styled(o["state"]) + (" [yellow]blocked[/yellow]" if o.get("blocked") else ""),
            parts,
            _when(o["created"]),
            due,
            o["note"],
        )
    print_table(table)


@click.command()
@click.argument("order_id", metavar="ORDER")
@click.pass_context
def cancel(ctx: click.Context, order_id: str) -> None:
    """Cancel order ORDER if no part of it has started."""
    console.print(cell_call(ctx, "orders.cancel", {"id": order_id})["message"], markup=False)


def _report_dict(r: Report) -> dict[str, object]:
    return {
        "seq": r.seq,
        "time": r.time,
        "kind": r.kind,
        "order_id": r.order_id,
        "part_id": r.part_id,
        "text": r.text,
    }


def _report_row(r: Report) -> tuple[str, ...]:
    return (str(r.seq), _when(r.time), r.kind, r.order_id or "", r.part_id or "", r.text)


@click.command()
@click.option("--since", type=int, default=0, metavar="SEQ", help="Only reports after SEQ.")
@click.option("--limit", type=click.IntRange(min=1), help="At most this many.")
@click.option("--follow", "-f", is_flag=True, help="Keep printing new reports until Ctrl-C.")
@json_option
@click.pass_context
def reports(ctx: click.Context, since: int, limit: int | None, follow: bool, as_json: bool) -> None:
    """List the reports the cell posted (order accepted, steps, alarms, parts, order done)."""
    directory = cell_dir(ctx)
    columns = ("Seq", "Time", "Kind", "Order", "Part", "Text")

    if follow:

        async def follow_reports() -> None:
            seen = since
            with open_mailbox(directory) as mailbox:

                async def step() -> None:
                    nonlocal seen
                    for r in mailbox.reports(seen):
                        if as_json:  # one JSON object a line, as it comes
                            click.echo(json.dumps(_report_dict(r), ensure_ascii=False))
                        else:
                            print_line("  ".join(x for x in _report_row(r) if x))
                        console.file.flush()
                        seen = r.seq

                await follow_until_stopped(step, FOLLOW_POLL)

        run(follow_reports)
        return

    def action() -> None:
        if not (directory / MAILBOX_FILE).exists():
            from cellctl.service.client import require_cell

            require_cell(directory)  # a mistyped --cell is not an empty cell
            if as_json:
                print_json([])
                return
            console.print(f"no reports (no mailbox in {directory})")
            return
        with open_mailbox(directory) as mailbox:
            found = mailbox.reports(since, limit)
        if as_json:
            print_json([_report_dict(r) for r in found])
            return
        if not found:
            console.print("no reports")
            return
        table = Table(title="Reports")
        for column in columns:
            table.add_column(column, justify="right" if column == "Seq" else "left")
        for r in found:
            table.add_row(*_report_row(r))
        print_table(table)

    _run(action)


# -- alarms ---------------------------------------------------------------------------------------


@click.group()
def alarm() -> None:
    """The cell's alarms: list, acknowledge, shelve, unshelve, clear; their history."""


@alarm.command("list")
@click.option("--all", "show_all", is_flag=True, help="Cleared alarms too.")
@json_option
@click.pass_context
def alarm_list(ctx: click.Context, show_all: bool, as_json: bool) -> None:
    """List active alarms (all of them with --all)."""
    found = cell_call(ctx, "alarms.list", {"all": show_all})
    if as_json:
        print_json(found)
        return
    if not found:
        console.print("no alarms" if show_all else "no active alarms")
        return
    table = Table(title="Alarms")
    for column in ("Id", "Raised", "Priority", "Machine", "Code", "Text", "State", "Cleared"):
        table.add_column(column, justify="right" if column == "Id" else "left")
    for a in found:
        state = alarm_state(a, current_clock().now())
        state = f"[red]{state}[/red]" if "UNACKED" in state else state
        cleared = f"{_when(a['cleared'])} by {a['cleared_by']}" if a["cleared"] else ""
        table.add_row(
            str(a["id"]),
            _when(a["raised"]),
            str(a.get("priority", "")),
            a["machine"],
            a["code"],
            a["text"],
            state,
            cleared,
        )
    print_table(table)


@alarm.command("clear")
@click.argument("alarm_id", metavar="ID", type=int)
@click.pass_context
def alarm_clear(ctx: click.Context, alarm_id: int) -> None:
    """Clear alarm ID once its cause is dealt with: the action that ends an alarm."""
    console.print(cell_call(ctx, "alarms.clear", {"id": alarm_id})["message"])


@alarm.command("ack")
@click.argument("alarm_id", metavar="ID", type=int)
@click.pass_context
def alarm_ack(ctx: click.Context, alarm_id: int) -> None:
    """Acknowledge alarm ID: seen; it stays open until cleared."""
    console.print(cell_call(ctx, "alarms.ack", {"id": alarm_id})["message"])


@alarm.command("shelve")
@click.argument("alarm_id", metavar="ID", type=int)
@click.option(
    "--for",
    "duration",
    required=True,
    metavar="TIME",
    help="How long: 30m, 2h, 1h30m, 90s (at most 8h).",
)
@click.pass_context
def alarm_shelve(ctx: click.Context, alarm_id: int, duration: str) -> None:
    """Shelve alarm ID for a time: not shown as unacknowledged until it runs out."""
    again = f" (to show it again now: cellctl alarm unshelve {alarm_id})"
    seconds = _seconds(duration, "--for", zero=again)
    if seconds > MAX_SHELVE:
        raise click.BadParameter(f"{duration}: at most 8h", param_hint="--for")
    result = cell_call(ctx, "alarms.shelve", {"id": alarm_id, "seconds": seconds})
    console.print(result["message"])


@alarm.command("unshelve")
@click.argument("alarm_id", metavar="ID", type=int)
@click.pass_context
def alarm_unshelve(ctx: click.Context, alarm_id: int) -> None:
    """Unshelve alarm ID before its time runs out: shown as it is again at once."""
    console.print(cell_call(ctx, "alarms.unshelve", {"id": alarm_id})["message"])


@alarm.command("history")
@click.option("--since", metavar="TIME", help="Raised since: 2h ago (2h, 30m) or a date/time.")
@click.option("--machine", metavar="NAME", help="Only this machine's (cell, plc, robot, ...).")
@click.option("--priority", type=click.Choice(PRIORITIES), help="Only this priority.")
@json_option
@click.pass_context
def alarm_history(
    ctx: click.Context, since: str | None, machine: str | None, priority: str | None, as_json: bool
) -> None:
    """Every alarm the journal holds, oldest first, with its states."""
    params: dict[str, object] = {}
    if since is not None:
        params["since"] = _since(since)
    if machine is not None:
        params["machine"] = machine
    if priority is not None:
        params["priority"] = priority
    found = cell_call(ctx, "alarms.history", params)
    if as_json:
        print_json(found)
        return
    if not found:
        console.print("no alarms")
        return
    table = Table(title="Alarm history")
    for column in ("Id", "Raised", "Pri", "Machine", "Code", "Text", "State"):
        table.add_column(column, justify="right" if column == "Id" else "left")
    for a in found:
        table.add_row(
            str(a["id"]),
            _when(a["raised"]),
            a["priority"],
            a["machine"],
            a["code"],
            a["text"],
            alarm_state(a, current_clock().now()),
        )
    print_table(table)


def alarm_state(a: dict[str, Any], now: float) -> str:
    """An alarm's states in a control room's words: cleared, or unacknowledged/acknowledged,
    active/returned to normal, shelved."""
    if a["state"] == "cleared":
        return f"cleared {_when(a['cleared'])} by {a['cleared_by']}"
    words = ["acked" if a["acked"] is not None else "UNACKED"]
    words.append("active" if a["returned"] is None else "returned")
    if a["shelved_until"] is not None and a["shelved_until"] > now:
        words.append(f"shelved until {_when(a['shelved_until'])}")
    return ", ".join(words)


_UNITS = {"h": 3600.0, "m": 60.0, "s": 1.0}


def _seconds(text: str, option: str, zero: str = "") -> float:
    """``30m``, ``2h``, ``1h30m``, ``90s``, ``45`` (seconds) as seconds; refused otherwise
    (no time at all: with ``zero`` said after the refusal, e.g. what to do instead)."""
    parts = re.fullmatch(r"(?:(\d+)h)?(?:(\d+)m)?(?:(\d+)s?)?", text.strip())
    if not text.strip() or parts is None:
        raise click.BadParameter(f"{text!r}: say 30m, 2h, 1h30m or 90s", param_hint=option)
    h, m, s = (int(g) if g else 0 for g in parts.groups())
    seconds = h * 3600.0 + m * 60.0 + s
    if seconds <= 0:
        raise click.BadParameter(f"{text!r}: more than 0 s{zero}", param_hint=option)
    return seconds


def _since(text: str) -> float:
    """``2h`` (ago) or an ISO date/time, as s since the epoch."""
    if re.fullmatch(r"\s*\d+[hms](\d+[hms])*\s*", text):
        return current_clock().now() - _seconds(text, "--since")
    try:
        return datetime.fromisoformat(text.strip()).timestamp()
    except (ValueError, OverflowError, OSError):
        raise click.BadParameter(
            f"{text!r}: say 2h (ago) or a date/time like 2026-11-25T08:00", param_hint="--since"
        ) from None


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
@json_option
@click.pass_context
def part_list(
    ctx: click.Context, statuses: Sequence[str], order_id: str | None, as_json: bool
) -> None:
    """List parts: where each is, how far along its route, and why it is held."""
    found = cell_call(ctx, "parts.list", {"statuses": list(statuses) or None, "order": order_id})
    if as_json:
        print_json(found)
        return
    if not found:
        console.print("no parts")
        return
    # The part's whole id, as reports and events name it (it begins with its order's id).
    table = Table(title="Parts (release and scrap take the id, or its order's id cut short)")
    for column in ("Part", "Type", "Location", "Route", "Status", "Note"):
        table.add_column(
            column, justify="right" if column == "Route" else "left", no_wrap=column == "Part"
        )
    for p in found:
        # A held part the arm may have put down elsewhere: every place it may be.
        others = [m for m in p.get("may_be_in", []) if m != p["location"]]
        table.add_row(
            p["id"],
            p["part_type"],
            " or ".join([p["location"], *others]) + ("?" if others else ""),
            str(p["route_index"]),
            _styled(p["status"]),
            p["note"],
        )
    print_table(table)


@part.command("release")
@click.argument("part_id", metavar="ID")
@click.option("--redo", is_flag=True, help="Run the interrupted step again (default: it is done).")
@click.option(
    "--at",
    "location",
    metavar="LOCATION",
    help="Where the part is now: the conveyor, the mill it was cut in or is to be cut in next "
    "(e.g. cnc1), or out (the outfeed, its route done); needed after an interrupted transfer.",
)
@click.pass_context
def part_release(ctx: click.Context, part_id: str, redo: bool, location: str | None) -> None:
    """Release held part ID after inspection: the cell carries on with it."""
    params: dict[str, object] = {"id": part_id, "redo": redo}
    if location is not None:
        params["at"] = location
    console.print(cell_call(ctx, "parts.release", params)["message"])


@part.command("scrap")
@click.argument("part_id", metavar="ID")
@click.option(
    "--reason",
    default="scrapped by operator",
    show_default=True,
    help="Why (kept in the journal).",
)
@click.option(
    "--taken-out",
    is_flag=True,
    help="It is out of the machine it was in (needed for a part in a machine: the cell "
    "loads that machine again at once).",
)
@click.pass_context
def part_scrap(ctx: click.Context, part_id: str, reason: str, taken_out: bool) -> None:
    """Scrap part ID (held or waiting): the cell will not work on it again."""
    params = {"id": part_id, "reason": reason, "taken_out": taken_out}
    console.print(cell_call(ctx, "parts.scrap", params)["message"])


__all__ = ["alarm", "cancel", "orders", "part", "reports", "submit"]
