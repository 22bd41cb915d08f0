"""What a run made and how busy every machine was: the summary and the Gantt chart.

Both are read from the journal, so they describe any run, live or after the fact::

    summary = summarize(journal, machines=["robot", "cnc1", "cnc2"], since=t0)
    print("\\n".join(summary.lines()))
    write_gantt(journal, ["robot", "cnc1", "cnc2"], "gantt.svg", since=t0)
"""

from __future__ import annotations

from collections import Counter
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
    )


_COLORS = ["#4e79a7", "#f28e2b", "#59a14f", "#e15759", "#76b7b2", "#edc948", "#b07aa1"]


def gantt_svg(
    steps: list[Step],
    machines: list[str],
    *,
    part_types: dict[str, str] | None = None,
    since: float = 0.0,
    title: str = "",
) -> str:
    """An SVG Gantt chart: one row per machine, one bar per step, coloured by part type."""
    types = part_types or {}
    steps = [s for s in steps if s.ended is not None and s.started >= since]
    if not steps:
        return '<svg xmlns="http://www.w3.org/2000/svg" width="400" height="40"></svg>\n'
    t0 = min(s.started for s in steps)
    t1 = max(s.ended or s.started for s in steps)
    span = max(t1 - t0, 1e-6)
    left, width, row_h, top = 90, 900, 34, 40
    height = top + row_h * len(machines) + 40
    kinds = sorted({types.get(s.part_id, "") for s in steps})
    color = {k: _COLORS[i % len(_COLORS)] for i, k in enumerate(kinds)}
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{left + width + 20}" '
        f'height="{height}" font-family="sans-serif" font-size="12">',
        '<rect width="100%" height="100%" fill="white"/>',
        f'<text x="{left}" y="20" font-size="14">{escape(title)}</text>',
    ]
    for row, machine in enumerate(machines):
        y = top + row * row_h
        out.append(f'<text x="8" y="{y + 20}">{escape(machine)}</text>')
        out.append(
            f'<line x1="{left}" y1="{y + row_h - 2}" x2="{left + width}" '
            f'y2="{y + row_h - 2}" stroke="#ddd"/>'
        )
        for s in steps:
            if s.machine != machine or s.ended is None:
                continue
            x = left + (s.started - t0) / span * width
            w = max(1.0, (s.ended - s.started) / span * width)
            fill = "#999" if s.state != "finished" else color[types.get(s.part_id, "")]
            label = escape(f"{s.part_id} {s.program} {s.ended - s.started:.2f} s {s.state}")
            out.append(
                f'<rect x="{x:.1f}" y="{y + 4}" width="{w:.1f}" height="{row_h - 10}" '
                f'fill="{fill}" stroke="white"><title>{label}</title></rect>'
            )
    axis_y = top + row_h * len(machines) + 14
    for i in range(11):
        x = left + i * width / 10
        out.append(
            f'<text x="{x:.0f}" y="{axis_y}" text-anchor="middle">{span * i / 10:.1f}s</text>'
        )
    out.append("</svg>")
    return "\n".join(out) + "\n"


def write_gantt(journal: Journal, machines: list[str], path: str | Path, **kw: object) -> Path:
    """Write :func:`gantt_svg` of the journal's steps to ``path`` (parts coloured by type)."""
    types = {p.id: p.part_type for p in journal.parts()}
    svg = gantt_svg(journal.steps(), machines, part_types=types, **kw)  # type: ignore[arg-type]
    target = Path(path)
    target.write_text(svg, encoding="utf-8")
    return target
