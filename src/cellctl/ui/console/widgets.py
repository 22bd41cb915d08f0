"""The console's always-visible panes: the cell board (machines, alarms, orders), the result
of the last call (with a progress bar while one runs) and the selected machine's traffic.

The board renders the cell's status (:class:`~cellctl.service.status.CellStatus`, from the
JSON any API client gets) by field: a machine's condition, never a search of its words.
"""

from __future__ import annotations

import datetime as dt
import math
from typing import Any

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import ProgressBar, Static

from cellctl.clock import current_clock
from cellctl.kinds import Condition
from cellctl.service.status import AlarmInfo, CellMode, CellStatus, ProgressInfo, StepInfo

#: Characters of a progress bar drawn on the board.
BAR_WIDTH = 12


#: The fewest characters of the directory the header shows beside the console's state.
HEADER_PATH_MIN = 16


def header_text(state: str, where: str, directory: str, width: int) -> str:
    """The header in ``width`` columns: the console's ``state`` whole (wrapped only if it
    is wider than the screen), then ``where: DIRECTORY``, the directory cut at its start to
    fit (``cell: …/lab/cell``), on the next line if the state leaves too little room."""
    room = width - len(state) - len(f"  {where}: ")
    if room >= HEADER_PATH_MIN:
        return f"{state}  {where}: {_start_cut(directory, room)}"
    return f"{state}\n{where}: {_start_cut(directory, width - len(where) - 2)}"


def _start_cut(text: str, width: int) -> str:
    return text if len(text) <= width else "…" + text[len(text) - max(width - 1, 1) :]


def text_bar(done: float, total: float, width: int = BAR_WIDTH) -> str:
    """``█████░░░░░░░ 42%``."""
    fraction = min(max(done / total, 0.0), 1.0) if total > 0 else 0.0
    filled = round(fraction * width)
    return "█" * filled + "░" * (width - filled) + f" {fraction * 100:3.0f}%"


def _unacked(a: AlarmInfo, now: float) -> bool:
    """Open, unacknowledged and not shelved: shown until the operator acknowledges it."""
    shelved = a.shelved_until is not None and a.shelved_until > now
    return a.state == "active" and a.acked is None and not shelved


def due_text(due: float | None, late: bool = False) -> str:
    """An order's due time as the console shows it, short and local on the 24-hour clock:
    ``due Fri 11-27 18:00`` (its seconds only when it has some; the dashboard's form),
    ``LATE`` after it once the order is late; "" for an order without one."""
    if due is None:
        return ""
    moment = dt.datetime.fromtimestamp(due)
    shown = moment.strftime("%a %m-%d %H:%M" + (":%S" if moment.second else ""))
    return f"due {shown}" + (" LATE" if late else "")


def _clip(text: str, width: int) -> str:
    return text if len(text) <= width else text[: max(width - 1, 0)] + "…"


#: How the board names each condition (six characters at most; the colour says the rest).
CONDITION_LABELS = {
    Condition.OFFLINE: ("offln", "red"),
    Condition.NOT_READY: ("notrdy", "yellow"),
    Condition.IDLE: ("idle", "green"),
    Condition.BUSY: ("busy", "cyan"),
    Condition.ALARM: ("ALARM", "bold red"),
    Condition.OUT_OF_SERVICE: ("OUT", "yellow"),
}


def step_text(step: StepInfo | None) -> str:
    """A step for the eye: ``transfer conveyor_cnc1 A-1``."""
    if step is None:
        return ""
    return " ".join(x for x in (step.what.value, step.program, step.part_id) if x)


def progress_text(p: ProgressInfo, width: int | None = None) -> str:
    """``sending block 2/5 12 s left``: the phase, the block, the time left; in ``width``
    columns the words shorten (``send b2/5 12s left``, then ``b2/5 12s left``), never the
    figures."""
    _, left = p.estimated(current_clock().now())  # the run's estimate moves on through a cut
    shown_left = left is not None and math.isfinite(left)
    block = f"{p.block}/{p.blocks}" if p.blocks else ""
    forms = [
        [p.phase, f"block {block}" if block else "", f"{left:.0f} s left" if shown_left else ""],
        [p.phase, f"b{block}" if block else "", f"{left:.0f}s left" if shown_left else ""],
        [p.phase[:4], f"b{block}" if block else "", f"{left:.0f}s left" if shown_left else ""],
        [f"b{block}" if block else "", f"{left:.0f}s left" if shown_left else ""],
        [f"b{block}" if block else "", f"{left:.0f}s" if shown_left else ""],
    ]
    texts = [" ".join(w for w in words if w) for words in forms]
    if width is None:
        return texts[0]
    return next((t for t in texts if len(t) <= width), texts[-1])


def counted_text(p: ProgressInfo) -> str | None:
    """``2345/5600 chars``: a progress counted in its unit, not in blocks (None otherwise)."""
    if p.blocks or p.total <= 0 or not p.unit:
        return None
    return f"{p.done}/{p.total} {p.unit}"


def figures_text(p: ProgressInfo) -> str:
    """``960 chars/s 12 s left stall 0.4 s``: its rate, time left and the machine's stall
    time (each where the status has it)."""
    words = []
    if p.rate_per_s:
        words.append(f"{p.rate_per_s:.0f} {p.unit}/s")
    _, left = p.estimated(current_clock().now())
    if left is not None and math.isfinite(left):
        words.append(f"{left:.0f} s left")
    if p.stall_s is not None:
        words.append(f"stall {p.stall_s:.1f} s")
    return " ".join(words)


def board_text(snapshot: dict[str, Any] | CellStatus, width: int = 48, height: int = 0) -> Text:
    """The board: one line per machine (its condition, its state in its words), a second
    for its step and progress, or its trouble; open alarms, the order queue, events."""
    out = Text(no_wrap=True, overflow="ellipsis")
    status = snapshot if isinstance(snapshot, CellStatus) else CellStatus.model_validate(snapshot)
    cell = status.cell
    title = "MACHINES" + ("   CELL PAUSED" if cell.paused else "")
    if cell.mode is CellMode.EMERGENCY_STOP:
        title += "   EMERGENCY STOP"
    out.append(title + "\n", style="bold")
    for name, m in status.machines.items():
        out.append(f"{name:<6} ", style="bold")
        label, style = CONDITION_LABELS[m.condition]
        out.append(f"{label:<6} ", style=style)
        out.append(_clip(m.state, width - 14) + "\n")
        step = step_text(m.step)
        if m.progress is not None:
            bar = text_bar(m.progress.estimated(current_clock().now())[0], 1.0, 8)
            counted = counted_text(m.progress)
            if counted is not None:  # a transfer counted in its unit: figures a line below
                line = f"       {bar} {counted} {m.progress.phase} {step}"
                out.append(_clip(line.rstrip(), width) + "\n", style="cyan")
                figures = figures_text(m.progress)
                if figures:
                    out.append(_clip(f"       {figures}", width) + "\n", style="cyan")
            else:
                # The figures whole (their words shortened to fit), the step in what is left.
                line = f"       {bar} "
                line += progress_text(m.progress, width - len(line))
                room = width - len(line) - 1
                if step and room >= 2:
                    line += " " + _clip(step, room)
                out.append(_clip(line, width) + "\n", style="cyan")
        elif step:
            out.append(_clip(f"       {step}", width) + "\n")
        last = [a for a in status.alarms if a.machine == name]
        if last:
            out.append(_clip(f"       ! {last[-1].text}", width) + "\n", style="red")
        elif m.error is not None and m.condition in (Condition.ALARM, Condition.OFFLINE):
            out.append(_clip(f"       ! {m.error.text}", width) + "\n", style="red")
        elif m.condition is Condition.OUT_OF_SERVICE and m.out_reason:
            out.append(_clip(f"       {m.out_reason}", width) + "\n", style="yellow")
    alarms = status.alarms
    now = current_clock().now()
    unacked = [a for a in alarms if _unacked(a, now)]
    head = f"ALARMS {len(alarms)} open" + (f", {len(unacked)} UNACKED" if unacked else "")
    out.append(head + "\n", style="bold white on red" if unacked else "bold")
    for a in alarms[-3:]:
        mark = "!" if _unacked(a, now) else " "
        line = f"{mark}{a.id} {a.machine} {a.code}: {a.text}"
        out.append(_clip(line, width) + "\n", style="bold red" if mark == "!" else "red")
    orders = status.orders
    open_orders = [o for o in orders if o.state not in ("done", "cancelled", "failed")]
    out.append(f"ORDERS {len(open_orders)} open\n", style="bold")
    for o in (open_orders or orders[:3])[:6]:
        done = o.parts.get("done", 0)
        line = f" {o.id} {o.part_type} x{o.qty} p{o.priority} {o.state} {done}/{o.qty}"
        due = due_text(o.due, o.late)
        if due and len(line) + 1 + len(due) <= width:  # on its line when it fits, whole
            out.append(line + " ")
            out.append(due + "\n", style="bold red" if o.late else "")
        else:
            out.append(_clip(line, width) + "\n")
            if due:  # else on a line of its own, whole: LATE is never cut off
                out.append(_clip(f"   {due}", width) + "\n", style="bold red" if o.late else "")
        if o.blocked:  # its parts wait for a machine out of service: which, and why
            out.append(_clip(f"   BLOCKED {o.blocked.removeprefix('blocked: ')}", width) + "\n",
                       style="yellow")  # fmt: skip
    events = status.events
    room = height - len(out.plain.splitlines()) - 1
    if events and room > 0:
        out.append("EVENTS\n", style="bold")
        for e in events[-room:]:
            stamp = dt.datetime.fromtimestamp(e.time).strftime("%H:%M:%S")
            out.append(_clip(f" {stamp} {e.text}", width) + "\n", style="dim")
    out.rstrip()
    return out


#: Columns of a traffic row before its hex: ``14:02:07.123 >>* ``.
TRAFFIC_HEAD = 17
#: The most columns of a row's hex, and the fewest its text keeps.
TRAFFIC_HEX = 35
TRAFFIC_TEXT_MIN = 6


def traffic_text(
    machine: str,
    rows: list[dict[str, Any]],
    width: int = 78,
    command: dict[str, Any] | None = None,
) -> Text:
    """The last rows of a machine's traffic: time, direction, hex, text; the first bytes of
    the operator's own ``command`` on top (marked ``>>*``) when given."""
    out = Text(no_wrap=True, overflow="ellipsis")
    if not rows and command is None:
        out.append(f"no traffic on {machine} yet", style="dim")
        return out
    if command is not None:
        rows = [{**command, "dir": ">>*"}, *rows]
    # The hex column takes what the time, the direction and the least of the text leave.
    hex_width = max(min(TRAFFIC_HEX, width - TRAFFIC_HEAD - 1 - TRAFFIC_TEXT_MIN), 8)
    for i, row in enumerate(rows):
        stamp = dt.datetime.fromtimestamp(float(row.get("time", 0))).strftime("%H:%M:%S.%f")[:-3]
        direction = str(row.get("dir", ""))
        hex_text = _clip(str(row.get("hex", "")), hex_width)
        style = {">>": "green", ">>*": "bold green"}.get(direction, "cyan")
        line = Text(no_wrap=True, overflow="ellipsis")
        line.append(f"{stamp} {direction:<3} ", style=style)
        line.append(f"{hex_text:<{hex_width}} ")
        room = width - TRAFFIC_HEAD - hex_width - 1
        line.append(_clip(f"|{row.get('text', '')}|", max(room, 0)), style="dim")
        line.truncate(width, overflow="ellipsis")  # one row each, whatever the pane's width
        out.append_text(line)
        if i < len(rows) - 1:
            out.append("\n")
    return out


class Board(Static):
    """Every machine, the open alarms and the order queue (from the status snapshot)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.snapshot: dict[str, Any] = {}
        self._drawn: Text | None = None

    def show(self, snapshot: dict[str, Any]) -> None:
        self.snapshot = snapshot
        if snapshot:
            self._drawn = shown(
                self,
                board_text(snapshot, max(self.content_size.width, 30), self.content_size.height),
                self._drawn,
            )

    def on_resize(self) -> None:
        self.show(self.snapshot)


class TrafficPane(Static):
    """The selected machine's bytes both ways (``>>`` sent, ``<<`` received), the operator's
    own last command first (``>>*``)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._drawn: Text | None = None
        #: Per machine, the rows (and the operator's command) it showed last.
        self.seen: dict[str, tuple[list[dict[str, Any]], dict[str, Any] | None]] = {}

    def show(
        self, machine: str, rows: list[dict[str, Any]], command: dict[str, Any] | None = None
    ) -> None:
        """``command``: the first row sent for the operator's last command (shown first)."""
        self.seen[machine] = (rows, command)
        self._title(f"traffic: {machine} (>> sent, << received, >>* your command)")
        self.show_text(traffic_text(machine, rows, max(self.content_size.width, 40), command))

    def disconnected(self, machine: str) -> None:
        """No traffic to ask for (the controller's API closed): ``machine``'s last rows seen
        before, said to be so, or that none were."""
        self._title(f"traffic: {machine} (DISCONNECTED: the last bytes seen before)")
        if machine in self.seen:
            rows, command = self.seen[machine]
            self.show_text(traffic_text(machine, rows, max(self.content_size.width, 40), command))
        else:
            self.show_text(Text(f"no traffic seen on {machine} before the API closed", "dim"))

    def _title(self, title: str) -> None:
        if self.border_title != title:  # setting it redraws the pane, even to the same
            self.border_title = title

    def show_text(self, text: Text) -> None:
        """Show ``text`` (the traffic, or why there is none)."""
        self._drawn = shown(self, text, self._drawn)


def shown(widget: Static, text: Text, drawn: Text | None) -> Text:
    """``widget.update(text)`` unless ``drawn``, what it shows now, is the same; ``text``.

    An update lays the widget out and draws it again, and the status comes many times a
    second while a batch runs, mostly as it was: on a shop's old PC that is the console's CPU.
    """
    if drawn is None or _look(text) != _look(drawn):
        # A widget whose size its CSS fixes (the header, the board, the traffic pane) keeps
        # it whatever it shows: no layout of the whole screen for it, only its own redraw.
        widget.update(text, layout=not _sized(widget))
    return text


def _sized(widget: Static) -> bool:
    """True if ``widget``'s CSS fixes its height and its width is not ``auto`` (one left
    unset fills its container's)."""
    width, height = widget.styles.width, widget.styles.height
    return height is not None and not height.is_auto and (width is None or not width.is_auto)


def _look(text: Text) -> tuple[object, ...]:
    # Rich's Text == compares the characters and their spans, not the style of the whole.
    return (text.plain, text.spans, text.style, text.justify, text.overflow, text.no_wrap)


#: Rows the result pane shows (its height in the console's CSS).
RESULT_ROWS = 7


def fit_rows(lines: list[str], width: int, rows: int) -> list[str]:
    """``lines`` as they fit ``rows`` rows of ``width`` columns, wrapped: all of them if they
    fit, else the first (what the message is) and the newest that fit under a line saying
    how many were left out. A log's last lines are its newest: cut from the top, never the
    end."""
    width = max(width, 1)

    def height(line: str) -> int:
        return max(1, math.ceil(len(line) / width))

    if sum(height(line) for line in lines) <= rows or len(lines) < 2:
        return lines
    head, rest = lines[0], lines[1:]
    room = rows - height(head) - 1  # the note of what was left out takes a row
    kept: list[str] = []
    for line in reversed(rest):
        if height(line) > room:
            break
        kept.insert(0, line)
        room -= height(line)
    left = len(rest) - len(kept)
    return [head, f"… {left} earlier line{'s' if left != 1 else ''} not shown", *kept]


class ResultPane(Vertical):
    """The message of the last call (the source's words), and a bar while a call runs."""

    def compose(self) -> ComposeResult:
        yield Static(id="result-text")
        yield ProgressBar(id="call-progress", show_eta=False)

    def on_mount(self) -> None:
        self.query_one(ProgressBar).display = False

    def say(self, lines: list[str], style: str = "") -> None:
        shown = fit_rows(lines, self.content_size.width or self.app.size.width - 2, RESULT_ROWS)
        self.query_one("#result-text", Static).update(Text("\n".join(shown), style=style))

    def progress(self, done: float | None, total: float | None) -> None:
        """Show (or, with ``total`` None, hide) the call's progress bar."""
        bar = self.query_one(ProgressBar)
        if total is None:
            bar.display = False
            return
        bar.display = True
        bar.update(total=max(total, 1), progress=done or 0)
