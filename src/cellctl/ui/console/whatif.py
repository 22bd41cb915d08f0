"""The CELL menu's WHAT IF: a plan of the cell asked with a form and shown as text.

The form takes what ``cellctl plan`` takes (how far ahead, fault windows, orders to add, the
policy, the plan's poll period), checks it with :mod:`cellctl.plan`'s own parsers, and calls
the API's ``plan.run`` (the viewer role suffices) in the menu's worker: the board stays live
while the cell is played ahead on a copy. The answer is shown as ``cellctl plan`` prints it
(per order, when it finishes against its due time; parts made; utilizations), then a text
Gantt chart, one row per machine and one character per time slot (a terminal cannot show the
SVG)::

    params = plan_params({"horizon": "8h", "fault": "cnc2:down@10:00-11:00",
                          "add": "wax-robot-base:40", "policy": "default"}, now)
    answer = await plan_call(client, params, plan_span(params, now), shown.from_api)
    lines = plan_text(answer, Path("cell"))

It is waited for as ``cellctl plan`` waits (:func:`~cellctl.service.client.plan_call`: while
its play tells how far it has gone), how far on the result line in ``cellctl plan``'s words
(:class:`PlanProgress`).
"""

from __future__ import annotations

import contextlib
import io
import re
import textwrap
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Final

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import ScrollableContainer, Vertical
from textual.widgets import Static

from cellctl.errors import UsageError
from cellctl.ui.console.dialogs import Dialog, FieldRefused
from cellctl.ui.plan_progress import ProgressLine

if TYPE_CHECKING:
    from cellctl.plan.report import PlanReport

#: The view's columns (an 80-column terminal, less its padding).
LINE_WIDTH: Final = 78
#: Characters of the text Gantt chart's time axis.
GANTT_WIDTH: Final = 60
#: A slot where the machine is idle, in a fault window (and idle), in a failed step.
IDLE: Final = "."
FAULT: Final = "x"
FAILED: Final = "!"
#: How the form's fields separate several entries: orders at a comma or a semicolon, fault
#: windows at a semicolon only (a fault's argument may hold a comma), as the dashboard does.
ADD_SEPARATORS: Final = r"[,;]"
FAULT_SEPARATORS: Final = r";"
#: The largest seed a plan takes (the API's).
MAX_SEED: Final = 2**63 - 1
#: The form's field each refusal is about, by its first words: the parsers' (``duration
#: '8x': ...``, ``--add ...``, ``poll ...``) and the API's (``fault on 'cnc9': ...``,
#: ``order plan-add1: the cell makes no ...``, ``policy 'bogus': unknown ...``, and
#: ``plan.run: seed: ...`` for a parameter its schema refuses).
REFUSALS: Final = (
    ("horizon", r"(--)?(shift|until|duration|time)\b|'[^']*' is not a day|a plan's end|give --"),
    ("fault", r"(--)?fault\b"),
    ("add", r"(--)?add\b|order \S+: the cell makes no|nothing to plan"),
    ("policy", r"(--)?policy\b|no scheduler policy"),
    ("poll", r"(--)?poll\b"),
    ("seed", r"(--)?seed\b"),
)


def refusal_field(problem: str) -> str | None:
    """The form's field a refusal of the plan (the parsers' or the API's) is about, None
    for one about no field (``a plan is being played already``)."""
    text = problem.strip().removeprefix("plan.run: ")
    return next((field for field, words in REFUSALS if re.match(words, text)), None)


@contextlib.contextmanager
def refused_as(field: str) -> Iterator[None]:
    """A parser's refusal (its words) as a refusal of the form's ``field``."""
    try:
        yield
    except FieldRefused:
        raise
    except UsageError as e:
        raise FieldRefused(str(e), field) from None


def parse_seed(text: str) -> int:
    """The seed of anything random in the planned machines (a fault such as ``noise``)."""
    try:
        seed = int(text)
    except ValueError:
        seed = -1
    if not 0 <= seed <= MAX_SEED:
        raise UsageError(f"--seed {text!r}: a whole number 0 or more (at most {MAX_SEED})")
    return seed


def entries(text: str, separators: str) -> list[str]:
    """The non-empty entries of a field, trimmed."""
    return [s.strip() for s in re.split(separators, text) if s.strip()]


def plan_params(raw: dict[str, str], now: float) -> dict[str, Any]:
    """The form's answers as ``plan.run``'s parameters, each checked by the parser
    ``cellctl plan`` uses (a :class:`~cellctl.ui.console.dialogs.FieldRefused` in its words,
    naming the field). The horizon is a span (``8h``) or, when it holds a ``:``, a time
    (``FRI 18:00``); an empty poll or seed is the plan's own (5 s, 0)."""
    from cellctl.plan.spec import DEFAULT_SHIFT, parse_add, parse_fault, plan_window, policies_of
    from cellctl.plan.when import parse_poll

    horizon = raw.get("horizon", "").strip() or DEFAULT_SHIFT
    key = "until" if ":" in horizon else "shift"
    with refused_as("horizon"):
        end = plan_window(now, *((horizon, None) if key == "shift" else (None, horizon)))
    adds = entries(raw.get("add", ""), ADD_SEPARATORS)
    faults = entries(raw.get("fault", ""), FAULT_SEPARATORS)
    with refused_as("add"):
        for text in adds:
            parse_add(text)
    with refused_as("fault"):
        for text in faults:
            parse_fault(text, now, end)
    policy = raw.get("policy", "").strip() or "default"
    with refused_as("policy"):
        policies_of(policy)
    params: dict[str, Any] = {key: horizon, "add": adds, "fault": faults, "policy": policy}
    poll = raw.get("poll", "").strip()
    if poll:
        with refused_as("poll"):
            params["poll"] = parse_poll(poll)
    seed = raw.get("seed", "").strip()
    if seed:
        with refused_as("seed"):
            params["seed"] = parse_seed(seed)
    return params


def plan_span(params: dict[str, Any], now: float) -> float:
    """The span of the plan ``params`` (:func:`plan_params`' answer) asks for, s: how long
    it may take at most (:func:`~cellctl.service.client.plan_call`)."""
    from cellctl.plan.spec import plan_window

    return plan_window(now, params.get("shift"), params.get("until")) - now


class _Nowhere(io.StringIO):
    """A stream that keeps nothing: the progress line's words are read, never written."""

    def write(self, text: str) -> int:
        return len(text)


class PlanProgress:
    """How far a plan has played, in ``cellctl plan``'s words (``playing: 2:13:00 of
    8:00:00 machine time (28%, ...)``), from ``plan.run``'s progress: ``told(data)``, then
    ``text()`` and ``fraction()`` (of every policy's span, for a bar)."""

    def __init__(self, policies: int) -> None:
        self.line = ProgressLine(_Nowhere())
        self.policies = max(policies, 1)
        self.played: dict[str, float] = {}

    def told(self, data: dict[str, Any]) -> None:
        try:
            self.played[str(data["policy"])] = float(data["played_s"])
        except (KeyError, TypeError, ValueError):
            return  # not a plan's progress
        self.line.from_api(data)

    def text(self) -> str:
        return self.line.text() if self.played else "starting"

    def fraction(self) -> float:
        """The share of the plan played: every policy's machine time of its span."""
        span = max(self.line.span_s, 1e-9)
        return sum(min(s, span) for s in self.played.values()) / (span * self.policies)


def plan_text(answer: dict[str, Any], directory: Path) -> list[str]:
    """``plan.run``'s answer as the WHAT IF view shows it: ``cellctl plan``'s report, then
    each policy's text Gantt chart."""
    from cellctl.plan.report import policy_name
    from cellctl.plan.run import result_from_dict

    result = result_from_dict(answer["plan"], answer.get("svg", ""), directory)
    out: list[str] = []
    for report in result.reports:
        if out:
            out.append("")
        out += fitted(report_lines(report))
    # With several policies, the comparison ``cellctl plan`` prints after the plans.
    compared = result.lines()
    if len(result.reports) > 1 and "policies compared:" in compared:
        out += ["", *fitted(compared[compared.index("policies compared:") :])]
    for report in result.reports:
        out += ["", f"Gantt chart, policy {policy_name(report.policy)}:", *gantt_lines(report)]
    return out


def fitted(lines: list[str], width: int = LINE_WIDTH) -> list[str]:
    """``lines`` in ``width`` columns: a longer line goes on under itself, indented, broken
    after a comma in its second half (``... (policy downstream-first, seed 0,`` / ``poll 5
    s)``), else at a space (a word longer than a line, cut)."""
    out: list[str] = []
    for line in lines:
        indent = " " * min(len(line) - len(line.lstrip()) + 4, width // 2)
        while len(line) > width:
            comma = line.rfind(", ", 0, width)
            cut = comma + 1 if comma > width // 2 else line.rfind(" ", 0, width + 1)
            if cut <= len(indent):
                cut = width
            out.append(line[:cut].rstrip())
            line = indent + line[cut:].lstrip()
        out.append(line)
    return out


def report_lines(report: PlanReport) -> list[str]:
    """``cellctl plan``'s report, its order table narrowed to the console's 78 columns."""
    lines = report.lines()
    table = next(i for i, line in enumerate(lines) if line.startswith("order "))
    end = lines.index("", table)
    return [*lines[:table], *order_table(report), *lines[end:]]


def order_table(report: PlanReport) -> list[str]:
    """Per order: its part type, parts made, when it finishes (``not in plan``), its due
    time and its verdict (``late 0:12:00``; ``late >=1:00:00``: not finished, due passed)."""
    from cellctl.plan.report import LATE
    from cellctl.plan.when import span_text, when_text

    out = [f"{'order':<9} {'part type':<18} {'made':>5} {'finishes':<12} {'due':<12} verdict"]
    for o in report.orders:
        finishes = when_text(o.finished) if o.finished is not None else "not in plan"
        due = when_text(o.due) if o.due is not None else "-"
        verdict = o.verdict
        if o.verdict == LATE:
            verdict += f" {'>=' if o.finished is None else ''}{span_text(o.late_s)}"
        extra = f" held {o.held}" if o.held else ""
        extra += f" scrapped {o.scrapped}" if o.scrapped else ""
        made = f"{o.made}/{o.qty}"
        out.append(
            f"{o.order_id[:9]:<9} {o.part_type[:18]:<18} {made:>5} {finishes:<12} "
            f"{due:<12} {verdict}{extra}"
        )
    return out


def summary(answer: dict[str, Any], directory: Path) -> str:
    """One line for the result pane: the first policy's verdicts and its span."""
    from cellctl.plan.run import result_from_dict, summary_line

    return summary_line(result_from_dict(answer["plan"], answer.get("svg", ""), directory))


def _marks(report: PlanReport) -> dict[str, str]:
    """A letter per part type, in the order the plan first played them."""
    types = dict.fromkeys(str(s.get("part_type") or "?") for s in report.steps)
    letters = "ABCDEFGHIJKLMNOPQRSTUVWYZ"  # no X: the fault windows'
    return {t: letters[i] if i < len(letters) else "?" for i, t in enumerate(types)}


def _overlap(a: float, b: float, start: float, end: float) -> float:
    return min(b, end) - max(a, start)


def gantt_lines(report: PlanReport, width: int = GANTT_WIDTH) -> list[str]:
    """The plan as a text Gantt chart: one row per machine (the robot, then the mills), one
    character per slot of ``(until - start) / width`` seconds: the letter of the part type in
    the step that fills most of the slot (``!`` a step that failed), ``x`` a fault window
    where the machine is idle, ``.`` idle; then the time axis and the legend."""
    from cellctl.plan.when import span_text

    machines = list(report.utilization) or sorted({str(s["machine"]) for s in report.steps})
    label = max([7, *(len(m) for m in machines)])
    span = max(report.until - report.start, 1e-9)
    slot = span / width
    marks = _marks(report)
    rows = []
    for machine in machines:
        steps = [s for s in report.steps if s.get("machine") == machine]
        windows = [
            (f.start, f.end if f.end is not None else report.until)
            for f in report.faults
            if f.machine == machine
        ]
        cells = []
        for i in range(width):
            a, b = report.start + i * slot, report.start + (i + 1) * slot
            best, mark = 0.0, IDLE
            for s in steps:
                ended = s.get("ended")
                end = float(ended) if ended is not None else report.ended
                cover = _overlap(a, b, float(s["started"]), end)
                if cover > best:
                    failed = s.get("state") in ("failed", "interrupted")
                    best, mark = cover, FAILED if failed else marks[str(s.get("part_type") or "?")]
            if mark == IDLE and any(_overlap(a, b, w0, w1) > 0 for w0, w1 in windows):
                mark = FAULT
            cells.append(mark)
        rows.append(f"{machine:<{label}}|{''.join(cells)}|")
    rows.append(" " * (label + 1) + _axis(report.start, report.until, width))
    legend = [f"{m} {t}" for t, m in marks.items()]
    legend += [f"{FAILED} failed step", f"{FAULT} fault window", f"{IDLE} idle"]
    text = f"one character = {span_text(slot)}: " + ", ".join(legend)
    return rows + textwrap.wrap(text, LINE_WIDTH, break_on_hyphens=False)


def _axis(start: float, until: float, width: int) -> str:
    """The time axis: the start under the first slot, the middle, the end under the last."""
    span = until - start
    fmt = "%a %H:%M" if span > 20 * 3600 else "%H:%M" if span >= 600 else "%H:%M:%S"

    def at(stamp: float) -> str:
        return datetime.fromtimestamp(stamp).strftime(fmt)

    line = [" "] * width
    first, middle, last = at(start), at(start + span / 2), at(until)
    for i, c in enumerate(first):
        line[i] = c
    mid = (width - len(middle)) // 2
    if mid > len(first) and mid + len(middle) < width - len(last):
        line[mid : mid + len(middle)] = middle
    line[width - len(last) :] = last
    return "".join(line).rstrip()


class PlanView(Dialog[None]):
    """The plan's text, scrolled with the arrows and Page Up/Down; Escape or Enter closes."""

    BINDINGS: ClassVar[list[BindingType]] = [Binding("enter", "cancel", "Close")]
    # The whole screen, no border: 78 columns of text at 80, between a column of margin and
    # the scroll bar's.
    DEFAULT_CSS = """
    PlanView > Vertical {
        width: 100%; height: 100%; max-height: 100%; border: none; padding: 0 0 0 1;
    }
    PlanView #plan-scroll { height: 1fr; scrollbar-size-vertical: 1; }
    PlanView #plan-text { width: auto; }
    """

    def __init__(self, title: str, lines: list[str]) -> None:
        super().__init__()
        self.title_text = title
        self.lines = lines

    def compose(self) -> ComposeResult:
        with Vertical():
            yield Static(Text(self.title_text), classes="title")
            with ScrollableContainer(id="plan-scroll"):
                yield Static(Text("\n".join(self.lines), no_wrap=True), id="plan-text")
            yield Static("arrows / PgUp / PgDn scroll; Enter or Escape closes", classes="hint")

    def on_mount(self) -> None:
        self.query_one("#plan-scroll", ScrollableContainer).focus()
