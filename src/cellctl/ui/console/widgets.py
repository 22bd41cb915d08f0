"""The console's always-visible panes: the cell board (machines, alarms, orders), the result
of the last call (with a progress bar while one runs) and the selected machine's traffic.

Each pane renders from plain dicts (the API's status snapshot, ``traffic.tail`` rows), so
what it shows is what any API client would see.
"""

from __future__ import annotations

import datetime as dt
from typing import Any

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import ProgressBar, Static

#: Characters of a progress bar drawn on the board.
BAR_WIDTH = 12


def text_bar(done: float, total: float, width: int = BAR_WIDTH) -> str:
    """``█████░░░░░░░ 42%``."""
    fraction = min(max(done / total, 0.0), 1.0) if total > 0 else 0.0
    filled = round(fraction * width)
    return "█" * filled + "░" * (width - filled) + f" {fraction * 100:3.0f}%"


def _clip(text: str, width: int) -> str:
    return text if len(text) <= width else text[: max(width - 1, 0)] + "…"


def board_text(snapshot: dict[str, Any], width: int = 48, height: int = 0) -> Text:
    """The board: one line per machine (a second one for progress or trouble), open alarms,
    the order queue."""
    out = Text(no_wrap=True, overflow="ellipsis")
    cell = snapshot.get("cell", {})
    machines: dict[str, Any] = snapshot.get("machines", {})
    alarms: list[dict[str, Any]] = snapshot.get("alarms", [])
    title = "MACHINES" + ("   CELL PAUSED" if cell.get("paused") else "")
    out.append(title + "\n", style="bold")
    for name, m in machines.items():
        out.append(f"{name:<6} ", style="bold")
        if cell.get("mode") == "attached":
            if m.get("in_service"):
                out.append("in  ", style="green")
            else:
                out.append("OUT ", style="yellow")
        out.append(_clip(str(m.get("state", "")), width - 11) + "\n")
        step = str(m.get("step") or "")
        progress = m.get("progress")
        if progress:
            bar = text_bar(progress.get("done", 0), progress.get("total", 0), 8)
            line = f"       {bar} {progress.get('phase', '')} {step}"
            out.append(_clip(line, width) + "\n", style="cyan")
        elif step:
            out.append(_clip(f"       {step}", width) + "\n")
        last = [a for a in alarms if a.get("machine") == name]
        if last:
            out.append(_clip(f"       ! {last[-1].get('text', '')}", width) + "\n", style="red")
        elif not m.get("in_service") and m.get("out_reason") and cell.get("mode") == "attached":
            out.append(_clip(f"       {m['out_reason']}", width) + "\n", style="yellow")
    out.append(f"ALARMS {len(alarms)} open\n", style="bold red" if alarms else "bold")
    for a in alarms[-3:]:
        line = f" {a.get('id')} {a.get('machine')} {a.get('code')}: {a.get('text', '')}"
        out.append(_clip(line, width) + "\n", style="red")
    orders: list[dict[str, Any]] = snapshot.get("orders", [])
    open_orders = [o for o in orders if o.get("state") not in ("done", "cancelled", "failed")]
    out.append(f"ORDERS {len(open_orders)} open\n", style="bold")
    for o in (open_orders or orders[:3])[:6]:
        done = o.get("parts", {}).get("done", 0)
        line = (
            f" {o.get('id')} {o.get('part_type')} x{o.get('qty')} p{o.get('priority')} "
            f"{o.get('state')} {done}/{o.get('qty')}"
        )
        out.append(_clip(line, width) + "\n")
    events: list[dict[str, Any]] = snapshot.get("events", [])
    room = height - len(out.plain.splitlines()) - 1
    if events and room > 0:
        out.append("EVENTS\n", style="bold")
        for e in events[-room:]:
            stamp = dt.datetime.fromtimestamp(float(e.get("time", 0))).strftime("%H:%M:%S")
            out.append(_clip(f" {stamp} {e.get('text', '')}", width) + "\n", style="dim")
    out.rstrip()
    return out


def traffic_text(machine: str, rows: list[dict[str, Any]], width: int = 78) -> Text:
    """The last rows of a machine's traffic: time, direction, hex, text."""
    out = Text(no_wrap=True, overflow="ellipsis")
    if not rows:
        out.append(f"no traffic on {machine} yet", style="dim")
        return out
    for i, row in enumerate(rows):
        stamp = dt.datetime.fromtimestamp(float(row.get("time", 0))).strftime("%H:%M:%S.%f")[:-3]
        direction = str(row.get("dir", ""))
        hex_text = _clip(str(row.get("hex", "")), 35)
        style = "green" if direction == ">>" else "cyan"
        out.append(f"{stamp} {direction} ", style=style)
        out.append(f"{hex_text:<35} ")
        out.append(_clip(f"|{row.get('text', '')}|", max(width - 52, 4)), style="dim")
        if i < len(rows) - 1:
            out.append("\n")
    return out


class Board(Static):
    """Every machine, the open alarms and the order queue (from the status snapshot)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.snapshot: dict[str, Any] = {}

    def show(self, snapshot: dict[str, Any]) -> None:
        self.snapshot = snapshot
        self.update(board_text(snapshot, max(self.size.width, 30), self.size.height))

    def on_resize(self) -> None:
        self.show(self.snapshot)


class TrafficPane(Static):
    """The selected machine's bytes both ways (``>>`` sent, ``<<`` received)."""

    def show(self, machine: str, rows: list[dict[str, Any]]) -> None:
        self.border_title = f"traffic: {machine} (>> sent, << received)"
        self.update(traffic_text(machine, rows, max(self.size.width, 40)))


class ResultPane(Vertical):
    """The message of the last call (the source's words), and a bar while a call runs."""

    def compose(self) -> ComposeResult:
        yield Static(id="result-text")
        yield ProgressBar(id="call-progress", show_eta=False)

    def on_mount(self) -> None:
        self.query_one(ProgressBar).display = False

    def say(self, lines: list[str], style: str = "") -> None:
        text = Text("\n".join(lines), style=style)
        self.query_one("#result-text", Static).update(text)

    def progress(self, done: float | None, total: float | None) -> None:
        """Show (or, with ``total`` None, hide) the call's progress bar."""
        bar = self.query_one(ProgressBar)
        if total is None:
            bar.display = False
            return
        bar.display = True
        bar.update(total=max(total, 1), progress=done or 0)
