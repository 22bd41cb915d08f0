"""What a run made and how busy every machine was: the summary and the Gantt chart.

Both are read from the journal, so they describe any run, live or after the fact::

    summary = summarize(journal, machines=["robot", "cnc1", "cnc2"], since=t0)
    print("\\n".join(summary.lines()))
    write_gantt(journal, ["robot", "cnc1", "cnc2"], "gantt.svg", since=t0)
    # Two runs on one time axis:
    svg = gantt_runs_svg([GanttRun("run A", steps_a, types, t0_a), ...], machines)
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from html import escape
from pathlib import Path

from cellctl.cell.journal import Journal, Step


@dataclass
class Summary:
    """Figures of one run: parts per type, makespan, utilization, alarms."""

    parts_made: dict[str, int]
    parts_held: int
    parts_scrapped: int
    makespan_s: float
    busy_s: dict[str, float]
    alarms_raised: int
    alarms_cleared: int
    steps_failed: int
    extra: dict[str, float] = field(default_factory=dict)
    #: When the run began (the ``since`` it was summarized from; 0: its first step).
    started: float = 0.0

    def utilization(self, machine: str) -> float:
        """Busy time over makespan (0 for an empty run)."""
        return self.busy_s.get(machine, 0.0) / self.makespan_s if self.makespan_s > 0 else 0.0

    def lines(self, title: str = "") -> list[str]:
        """Readable lines for the terminal."""
        out = [title] if title else []
        made = ", ".join(f"{n} x {t}" for t, n in sorted(self.parts_made.items())) or "none"
        out.append(f"parts made: {made}")
        if self.parts_held or self.parts_scrapped:
            out.append(f"parts held: {self.parts_held}, scrapped: {self.parts_scrapped}")
        out.append(f"makespan: {self.makespan_s:.2f} s")
        for machine in self.busy_s:
            out.append(f"utilization {machine}: {self.utilization(machine):6.1%}")
        out.append(
            f"alarms raised: {self.alarms_raised}, cleared: {self.alarms_cleared}; "
            f"failed steps: {self.steps_failed}"
        )
        return out


def _in_run(step: Step, since: float) -> bool:
    return step.started >= since


def summarize(journal: Journal, machines: list[str], since: float = 0.0) -> Summary:
    """The figures of everything journaled since ``since`` (a time.time() value)."""
    steps = [s for s in journal.steps() if _in_run(s, since)]
    part_ids = {s.part_id for s in steps}
    parts = [p for p in journal.parts() if p.id in part_ids]
    made = Counter(p.part_type for p in parts if p.status == "done")
    ends = [s.ended for s in steps if s.ended is not None]
    makespan = (max(ends) - min(s.started for s in steps)) if ends else 0.0
    busy = {m: 0.0 for m in machines}
    for s in steps:
        if s.ended is not None and s.machine in busy:
            busy[s.machine] += s.ended - s.started
    alarms = [a for a in journal.alarms() if a.raised >= since]
    return Summary(
        parts_made=dict(made),
        parts_held=sum(p.status == "held" for p in parts),
        parts_scrapped=sum(p.status == "scrapped" for p in parts),
        makespan_s=makespan,
        busy_s=busy,
        alarms_raised=len(alarms),
        alarms_cleared=sum(a.state != "active" for a in alarms),
        steps_failed=sum(s.state in ("failed", "interrupted") for s in steps),
        started=since,
    )


_COLORS = ["#4e79a7", "#f28e2b", "#59a14f", "#e15759", "#76b7b2", "#edc948", "#b07aa1"]
_FAILED = "#999"
_START_UP = "#e8e8e8"
_WINDOW = "#c0392b"
#: The narrowest bar drawn (px): a robot transfer of a fraction of a second stays visible.
_MIN_BAR = 2.0
_LEFT, _WIDTH, _ROW, _TOP = 90, 900, 34, 40


@dataclass(frozen=True)
class GanttWindow:
    """A span shaded on one machine's row (a plan's fault window): times as the steps'."""

    machine: str
    start: float
    end: float
    label: str


@dataclass
class GanttRun:
    """One run for :func:`gantt_runs_svg`: its title, steps, each part's type (part id ->
    type) and its start (the axis' 0: the batch's start, so the time before the first step
    is on the chart too); ``windows``: spans shaded on a machine's row."""

    title: str
    steps: list[Step]
    part_types: dict[str, str]
    start: float
    windows: list[GanttWindow] = field(default_factory=list)


def gantt_svg(
    steps: list[Step],
    machines: list[str],
    *,
    part_types: dict[str, str] | None = None,
    since: float = 0.0,
    title: str = "",
    span: float | None = None,
) -> str:
    """An SVG Gantt chart: one row per machine, one bar per step, coloured by part type, with
    a legend. ``since``: the run's start (0: its first step), the axis' 0; ``span``: the
    axis' length in seconds (give two charts the same to compare them)."""
    done = [s for s in steps if s.ended is not None and s.started >= since]
    if not done:
        return '<svg xmlns="http://www.w3.org/2000/svg" width="400" height="40"></svg>\n'
    start = since if since > 0 else min(s.started for s in done)
    return gantt_runs_svg([GanttRun(title, done, part_types or {}, start)], machines, span=span)


def gantt_runs_svg(
    runs: list[GanttRun],
    machines: list[str],
    *,
    span: float | None = None,
    tick: Callable[[float], str] | None = None,
) -> str:
    """Runs one above the other on one time axis (seconds from each run's start), with one
    legend: part types by colour, failed steps, and the start-up before a run's first step
    (the controller connecting: the robot initialized, the mills' setups sent). ``tick``:
    the axis' labels from seconds after the start (default ``12.5 s``)."""
    kinds = sorted({r.part_types.get(s.part_id, "") for r in runs for s in r.steps})
    color = {k: _COLORS[i % len(_COLORS)] for i, k in enumerate(kinds)}
    ends = [s.ended - r.start for r in runs for s in r.steps if s.ended is not None]
    axis = max(span or 0.0, max(ends, default=0.0), 1e-6)
    section = 24 + _ROW * len(machines)
    height = _TOP + section * len(runs) + 56
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{_LEFT + _WIDTH + 20}" '
        f'height="{height}" font-family="sans-serif" font-size="12">',
        '<rect width="100%" height="100%" fill="white"/>',
    ]
    for i, run in enumerate(runs):
        out += _gantt_rows(run, machines, _TOP - 20 + i * section, axis, color)
    axis_y = _TOP + section * len(runs) - 6
    for i in range(11):
        x = _LEFT + i * _WIDTH / 10
        text = tick(axis * i / 10) if tick is not None else f"{axis * i / 10:.1f} s"
        out.append(f'<text x="{x:.0f}" y="{axis_y}" text-anchor="middle">{escape(text)}</text>')
    out += _gantt_legend(color, axis_y + 22, windows=any(r.windows for r in runs))
    out.append("</svg>")
    return "\n".join(out) + "\n"


def _gantt_rows(
    run: GanttRun, machines: list[str], top: float, axis: float, color: dict[str, str]
) -> list[str]:
    out = [f'<text x="{_LEFT}" y="{top + 14}" font-size="14">{escape(run.title)}</text>']
    first = min((s.started for s in run.steps), default=run.start)
    y0 = top + 20
    if first > run.start:
        w = (first - run.start) / axis * _WIDTH
        out.append(
            f'<rect x="{_LEFT}" y="{y0}" width="{w:.1f}" height="{_ROW * len(machines)}" '
            f'fill="{_START_UP}" class="start-up"><title>start-up '
            f"{first - run.start:.2f} s</title></rect>"
        )
    for row, machine in enumerate(machines):
        y = y0 + row * _ROW
        out.append(f'<text x="8" y="{y + 20}">{escape(machine)}</text>')
        out.append(
            f'<line x1="{_LEFT}" y1="{y + _ROW - 2}" x2="{_LEFT + _WIDTH}" '
            f'y2="{y + _ROW - 2}" stroke="#ddd"/>'
        )
        for s in run.steps:
            if s.machine != machine or s.ended is None:
                continue
            x = _LEFT + (s.started - run.start) / axis * _WIDTH
            w = max(_MIN_BAR, (s.ended - s.started) / axis * _WIDTH)
            fill = _FAILED if s.state != "finished" else color[run.part_types.get(s.part_id, "")]
            label = escape(f"{s.part_id} {s.program} {s.ended - s.started:.2f} s {s.state}")
            out.append(
                f'<rect x="{x:.1f}" y="{y + 4}" width="{w:.1f}" height="{_ROW - 10}" '
                f'fill="{fill}" stroke="white" class="step {escape(s.kind)}">'
                f"<title>{label}</title></rect>"
            )
        for win in run.windows:
            if win.machine != machine or win.end <= run.start:
                continue
            x = _LEFT + max(0.0, win.start - run.start) / axis * _WIDTH
            w = max(_MIN_BAR, (win.end - max(win.start, run.start)) / axis * _WIDTH)
            out.append(
                f'<rect x="{x:.1f}" y="{y + 1}" width="{w:.1f}" height="{_ROW - 4}" '
                f'fill="{_WINDOW}" fill-opacity="0.25" stroke="{_WINDOW}" '
                f'stroke-dasharray="4 2" class="window"><title>{escape(win.label)} '
                f"{win.end - win.start:.0f} s</title></rect>"
            )
    return out


def _gantt_legend(color: dict[str, str], y: float, *, windows: bool = False) -> list[str]:
    entries = [(c, kind or "unknown part type") for kind, c in color.items()]
    entries += [(_FAILED, "failed or interrupted"), (_START_UP, "start-up (connecting)")]
    if windows:
        entries.append((_WINDOW, "fault window"))
    out = ['<g class="legend">']
    x = float(_LEFT)
    for fill, name in entries:
        out.append(f'<rect x="{x:.0f}" y="{y - 10}" width="12" height="12" fill="{fill}"/>')
        out.append(f'<text x="{x + 16:.0f}" y="{y}">{escape(name)}</text>')
        x += 30 + 7 * len(name)
    out.append("</g>")
    return out


def write_gantt(journal: Journal, machines: list[str], path: str | Path, **kw: object) -> Path:
    """Write :func:`gantt_svg` of the journal's steps to ``path`` (parts coloured by type)."""
    types = {p.id: p.part_type for p in journal.parts()}
    svg = gantt_svg(journal.steps(), machines, part_types=types, **kw)  # type: ignore[arg-type]
    target = Path(path)
    target.write_text(svg, encoding="utf-8")
    return target
