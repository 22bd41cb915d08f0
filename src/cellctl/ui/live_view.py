"""``cellctl run``'s live view: a header (the cell, its time scale, how to stop), a banner
while the cell is paused or in an emergency stop, the orders (each with its due time, and
LATE once late, as ``cellctl orders`` shows them), the machines with the reason of one out of
service, the open alarms, and the events, as many as the terminal has room for.

It renders the cell's status (:class:`~cellctl.service.status.CellStatus`, what every other
surface shows) and the controller's event list::

    view = LiveView(controller, directory)
    with Live(view.render(console), console=console) as screen:
        screen.update(view.render(console))
"""

from __future__ import annotations

import time
from pathlib import Path

from rich.console import Console, Group, RenderableType
from rich.table import Table
from rich.text import Text

from cellctl.cell.controller import CellController
from cellctl.clock import current_clock
from cellctl.emulators.header import emulated_scale
from cellctl.service.access import AttachedCell
from cellctl.service.status import CellMode, CellStatus
from cellctl.ui.alarm_marks import alarm_marks
from cellctl.ui.orders_cli import due_cell

#: Orders and alarms shown at most (the rest of the height goes to the events).
ORDER_ROWS = 12
ALARM_ROWS = 6
#: Events shown at least, however small the terminal.
MIN_EVENTS = 1
STOP_HINT = "Ctrl-C stops (steps in flight finish first; Ctrl-C again aborts)"


def time_scale_text(directory: Path) -> str:
    """``time scale 100 (emulated cell)`` for a cell ``cellctl emulate cell`` wrote, else
    ``real time``."""
    scale = emulated_scale(directory / "cell.toml")
    return f"time scale {scale} (emulated cell)" if scale is not None else "real time"


class LiveView:
    """What ``cellctl run`` shows on a terminal (see the module docstring)."""

    def __init__(self, controller: CellController, directory: Path) -> None:
        self.controller = controller
        self.access = AttachedCell(controller)
        self.directory = directory
        self.scale = time_scale_text(directory)

    def render(self, console: Console) -> RenderableType:
        """The whole view, its events pane as tall as the terminal leaves room for."""
        status = self.access.status()
        top = Group(
            *self.header(status), *self.banner(status), self.orders(status), self.machines(status)
        )
        alarms = self.alarms(status)
        used = len(console.render_lines(Group(top, alarms), console.options, pad=False))
        # An events table takes its title and two rules besides its rows.
        rows = max(console.height - used - 3, MIN_EVENTS)
        return Group(top, alarms, self.events(rows))

    def header(self, status: CellStatus) -> list[Text]:
        cell = status.cell
        clock = time.strftime("%H:%M:%S", time.localtime(cell.time))
        first = Text(no_wrap=True, overflow="ellipsis")
        first.append(f"cellctl run: cell {cell.name}", style="bold")
        first.append(f"  {self.directory}  {clock}")
        second = Text(f"{self.scale} · {STOP_HINT}", style="dim", no_wrap=True)
        second.overflow = "ellipsis"
        return [first, second]

    def banner(self, status: CellStatus) -> list[Text]:
        """A line in reverse colours while the cell does not dispatch: why, and the way out."""
        mode = status.cell.mode
        if mode is CellMode.EMERGENCY_STOP:
            stops = [a for a in status.alarms if a.code == "estop"]
            # The alarm's own words without their "emergency stop" (the banner says it).
            why = [a.text.removeprefix("emergency stop").lstrip(": ") for a in stops]
            reason = "; ".join(w for w in why if w) or "the PLC's emergency stop input is open"
            # A button to release only where the PLC's input says one is pressed.
            pressed = not stops or any(a.machine == "plc" for a in stops)
            way_out = "Release it, clear" if pressed else "Deal with its cause, clear"
            ids = ", ".join(str(a.id) for a in stops) or "ID"
            text = (
                f" EMERGENCY STOP: {reason}. {way_out} the alarm "
                f"(`cellctl alarm clear {ids}`), then `cellctl resume`. "
            )
            return [Text(text, style="bold white on red")]
        if mode is CellMode.STOPPING:
            return [
                Text(" STOPPING: the steps in flight finish first ", style="bold black on yellow")
            ]
        if status.cell.paused:
            text = " PAUSED: no new step starts (steps in flight finish). `cellctl resume` "
            return [Text(text, style="bold black on yellow")]
        return []

    def orders(self, status: CellStatus) -> Table:
        table = Table(title="orders", expand=True)
        for col in ("order", "part", "qty", "state", "done", "held", "due"):
            table.add_column(col)
        for o in status.orders[:ORDER_ROWS]:
            done, held = o.parts.get("done", 0), o.parts.get("held", 0)
            # As `cellctl orders` shows it: the same words on every terminal surface.
            due = due_cell(o.due, o.late)
            table.add_row(o.id, o.part_type, str(o.qty), o.state, str(done), str(held), due)
        return table

    def machines(self, status: CellStatus) -> Table:
        table = Table(title="machines", expand=True)
        for col in ("machine", "state", "current step", "service"):
            table.add_column(col)
        steps = {v.name: v.step for v in self.controller.machines.values()}
        for m in status.machines.values():
            if m.family == "plc":
                continue
            service = (
                "in service"
                if m.in_service
                else Text(f"OUT: {m.out_reason}".rstrip(": "), style="bold red")
            )
            table.add_row(m.name, m.state, steps.get(m.name, ""), service)
        return table

    def alarms(self, status: CellStatus) -> RenderableType:
        if not status.alarms:
            return Text("open alarms: none", style="dim", justify="center")
        table = Table(title="open alarms", expand=True)
        for col in ("id", "machine", "priority", "state", "alarm"):
            table.add_column(col)
        now = current_clock().now()
        for a in status.alarms[-ALARM_ROWS:]:
            # RTN: its condition is gone, the alarm open until cleared (not a fault now).
            state = alarm_marks(
                acked=a.acked, returned=a.returned, shelved_until=a.shelved_until, now=now
            )
            table.add_row(str(a.id), a.machine, a.priority, state, a.text)
        return table

    def events(self, rows: int) -> Table:
        table = Table(title="events", expand=True, show_header=False)
        table.add_column("time", width=8, min_width=8, no_wrap=True)
        # A line each (the rows fit the room); the event's text gives way, never the time.
        table.add_column("event", no_wrap=True, overflow="ellipsis", ratio=1)
        for e in self.controller.events[-rows:]:
            table.add_row(time.strftime("%H:%M:%S", time.localtime(e.time)), e.text)
        return table
