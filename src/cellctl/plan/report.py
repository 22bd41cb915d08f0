"""What a plan says: per order what finishes when against its due time, parts made, each
machine's utilization, and the Gantt chart. Read from a journal, so the same code reports a
plan (the engine's journal) and a real run (a cell's)::

    report = plan_report(journal, config, orders, start=t0, ended=t1, until=t1)
    print("\\n".join(report.lines()))
    Path("plan.json").write_text(json.dumps(report.as_dict()))
    Path("plan.svg").write_text(plan_svg([report], journal_steps, part_types))

An order finishes when the last of its parts is done; it is late when that is after its due
time, or when its due time passed within the plan and it did not finish. Only what is done by
the plan's end counts: a step still running then (the controller lets it end, as on Ctrl-C)
is shown running up to the end (:func:`within`), and its part is not made in the plan.
Utilization is a machine's time in steps over the plan's span (start to the time the plan
stopped: every order done, or its end), as the shift report counts availability, less its time
down: a machine's down time (out of service, or alarmed: the shift report's) counts as down,
not also as busy, so its busy and down shares add up to at most the whole span. A mill taken
out of service mid-cut finishes the cut, but that time is down time (the window the planner
gave), not utilization.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Final

from cellctl.cell.config import CellConfig
from cellctl.cell.journal import Journal, Step
from cellctl.cell.report import GanttRun, GanttWindow, gantt_runs_svg
from cellctl.cell.scheduler import DOWNSTREAM_FIRST
from cellctl.cell.shift import _down_intervals, _union, shift_report
from cellctl.plan.engine import FaultWindow, PlanOrder
from cellctl.plan.faults import PLC
from cellctl.plan.when import late_text, span_text, when_text

#: What an order's line says about it.
ON_TIME: Final = "on time"
LATE: Final = "late"
FINISHED: Final = "finished"  # no due time
OPEN: Final = "not finished"
VERDICTS: Final = (ON_TIME, LATE, FINISHED, OPEN)


@dataclass(frozen=True)
class OrderOutcome:
    """One order in the plan: its parts made, held and scrapped, when it finishes (None: not
    within the plan) and its verdict against its due time (:data:`VERDICTS`); ``late_s``: by
    how much it is late (at least, for one not finished)."""

    order_id: str
    part_type: str
    qty: int
    priority: int
    due: float | None
    made: int
    held: int
    scrapped: int
    finished: float | None
    verdict: str
    late_s: float = 0.0


#: The alarms a plan's text names one by one; beyond, their count.
ALARMS_SHOWN = 10


@dataclass
class PlanReport:
    """A plan's figures (see module docstring); :meth:`lines` for people, :meth:`as_dict`
    for programs (``plan.json``)."""

    cell: str
    policy: str
    seed: int
    start: float
    until: float
    ended: float
    wall_s: float
    orders: list[OrderOutcome]
    parts_made: dict[str, int]
    #: Each machine's busy time (in steps, not down) over the span: 0 to 1.
    utilization: dict[str, float]
    #: Time in steps while not down, s (down time counts as down only: see module docstring).
    busy_s: dict[str, float]
    #: Time out of service or alarmed, s; ``busy_s + down_s`` is at most the span.
    down_s: dict[str, float]
    faults: list[FaultWindow] = field(default_factory=list)
    alarms_raised: int = 0
    steps_failed: int = 0
    #: Parts held for the operator when the plan began (they stay held in it).
    held_at_start: int = 0
    #: Parts on their way when the plan began, taken up where they were.
    under_way_at_start: int = 0
    #: The steps played from the start: part, its type, kind, machine, program, state, times.
    steps: list[dict[str, Any]] = field(default_factory=list)
    #: How often the planned controller looked at idle machines, s (0: not known).
    poll_period: float = 0.0
    #: The alarms raised, in order: machine, code, text, raised (s since the epoch).
    alarms: list[dict[str, Any]] = field(default_factory=list)

    @property
    def on_time(self) -> int:
        return sum(o.verdict == ON_TIME for o in self.orders)

    @property
    def late(self) -> int:
        return sum(o.verdict == LATE for o in self.orders)

    @property
    def all_finished(self) -> bool:
        return all(o.finished is not None for o in self.orders)

    @property
    def last_finished(self) -> float | None:
        """When the last order finished (None: one did not, or there are none)."""
        ends = [o.finished for o in self.orders if o.finished is not None]
        return max(ends) if ends and len(ends) == len(self.orders) else None

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["on_time"], out["late"] = self.on_time, self.late
        out["all_finished"] = self.all_finished
        out["sim_s"] = self.ended - self.start
        return out

    def lines(self) -> list[str]:
        """The report for a terminal (80 columns)."""
        looks = f", poll {self.poll_period:g} s" if self.poll_period else ""
        out = [
            f"plan of {self.cell} (policy {policy_name(self.policy)}, seed {self.seed}{looks})",
            f"from {when_text(self.start, date=True)} to {when_text(self.until, date=True)} "
            f"({span_text(self.until - self.start)})",
        ]
        # A week or more: each weekday comes twice, so the day of the month is said too.
        long = self.until - self.start >= 7 * 86400

        def at(stamp: float) -> str:
            # A due time outside the plan (overdue, or a week on) with its date: its weekday
            # alone would read as a day of this plan.
            outside = not self.start - 1 <= stamp < max(self.until, self.start + 6 * 86400)
            return when_text(stamp, day=long, date=outside)

        # Each column as wide as its widest time (a weekday and time, unless a date is said).
        width = max(
            len(at(t)) for t in [self.start, *(o.finished for o in self.orders if o.finished)]
        )
        due_width = max(len(at(t)) for t in [self.start, *(o.due for o in self.orders if o.due)])
        for f in self.faults:
            end = at(f.end) if f.end is not None else "the end"
            what = f.fault + (f"={f.arg}" if f.arg else "")
            out.append(f"fault: {f.machine} {what} from {at(f.start)} to {end}")
        # Ids and part types whole, each column as wide as its longest (two ids alike but
        # for their ends must not read the same).
        ids = max([12, *(len(o.order_id) for o in self.orders)])
        types = max([20, *(len(o.part_type) for o in self.orders)])
        out += [
            "",
            f"{'order':<{ids}} {'part type':<{types}} {'made':>9}  {'finishes':<{width + 1}} due",
        ]
        for o in self.orders:
            finishes = at(o.finished) if o.finished is not None else "not in plan"
            due = at(o.due) if o.due is not None else "-"
            made = f"{o.made}/{o.qty}"
            extra = f" (held {o.held})" if o.held else ""
            extra += f" (scrapped {o.scrapped})" if o.scrapped else ""
            out.append(
                f"{o.order_id:<{ids}} {o.part_type:<{types}} {made:>9}  "
                f"{finishes:<{width + 1}} {due:<{due_width + 1}} {_verdict(o)}{extra}"
            )
        made = ", ".join(f"{n} x {t}" for t, n in sorted(self.parts_made.items())) or "none"
        out += ["", f"parts made: {made}"]
        util = ", ".join(f"{m} {u:.1%}" for m, u in self.utilization.items())
        out.append(f"utilization: {util}")
        span = max(self.ended - self.start, 1e-9)
        downs = ", ".join(
            f"{m} {span_text(s)} ({s / span:.1%})" for m, s in self.down_s.items() if s > 0
        )
        if downs:
            out.append(f"down: {downs}")
        if self.under_way_at_start:
            out.append(f"on their way at the start (taken up there): {self.under_way_at_start}")
        if self.held_at_start:
            out.append(f"held for the operator at the start (stay held): {self.held_at_start}")
        if self.alarms_raised or self.steps_failed:
            out.append(f"alarms raised: {self.alarms_raised}; failed steps: {self.steps_failed}")
        for a in self.alarms[:ALARMS_SHOWN]:
            out.append(f"alarm: {a['machine']} at {at(a['raised'])}: {a['text']}")
        if len(self.alarms) > ALARMS_SHOWN:
            out.append(
                f"... and {len(self.alarms) - ALARMS_SHOWN} more alarm(s) (--json lists them)"
            )
        last = self.last_finished
        if last is not None:
            out.append(
                f"every order finished by {at(last)} "
                f"({span_text(last - self.start)} after the start)"
            )
        else:
            missing = sum(o.finished is None for o in self.orders)
            out.append(f"{missing} order(s) not finished by {at(self.ended)}")
        out.append(
            f"on time {self.on_time}, late {self.late}; played "
            f"{span_text(self.ended - self.start)} in {self.wall_s:.1f} s"
        )
        return out


def policy_name(policy: str) -> str:
    """A policy as the plan's text names it: ``default`` by the policy it is
    (``downstream-first``), as ``--policy all`` names it."""
    return DOWNSTREAM_FIRST if policy == "default" else policy


def _verdict(o: OrderOutcome) -> str:
    """An order's verdict as its line says it: how late in one format (``late by 0:00:42``,
    ``late by at least 1:00:00``); one due as the plan ends and not finished then is late by
    an unknown time: "late: not finished when due", never "late by 0"."""
    if o.verdict != LATE:
        return o.verdict
    if o.finished is None:
        if o.late_s < 0.5:
            return f"{LATE}: not finished when due"
        return f"{LATE} by at least {late_text(o.late_s)}"
    return f"{LATE} by {late_text(o.late_s)}"


def within(steps: Sequence[Step], start: float, until: float) -> list[Step]:
    """The steps of a plan from ``start`` to ``until``: one still running at ``until`` (or
    ended after it) as running up to ``until``; none begun after it."""
    out = []
    for s in steps:
        if not start <= s.started < until:
            continue
        if s.ended is None or s.ended > until:
            s = replace(s, state="running", ended=until)
        out.append(s)
    return out


def _outcome(order: PlanOrder, journal: Journal, ended: float, until: float) -> OrderOutcome:
    parts = journal.parts(order_id=order.order_id)
    done = [p for p in parts if p.status == "done" and p.updated <= until]
    finished = max(p.updated for p in done) if len(done) >= order.qty and done else None
    late_s = 0.0
    if order.due is None:
        verdict = FINISHED if finished is not None else OPEN
    elif finished is not None:
        verdict = ON_TIME if finished <= order.due else LATE
        late_s = max(0.0, finished - order.due)
    elif order.due <= ended:
        verdict, late_s = LATE, ended - order.due
    else:
        verdict = OPEN
    return OrderOutcome(
        order.order_id,
        order.part_type,
        order.qty,
        order.priority,
        order.due,
        made=len(done),
        held=sum(p.status == "held" for p in parts),
        scrapped=sum(p.status == "scrapped" for p in parts),
        finished=finished,
        verdict=verdict,
        late_s=late_s,
    )


def machines_of(config: CellConfig) -> list[str]:
    """The machines a plan reports on: the robot, then the mills."""
    return [config.robot.name, *(m.name for m in config.mills)]


def plan_report(
    journal: Journal,
    config: CellConfig,
    orders: Sequence[PlanOrder],
    *,
    start: float,
    until: float,
    ended: float,
    wall_s: float = 0.0,
    policy: str = "default",
    seed: int = 0,
    faults: Sequence[FaultWindow] = (),
    held_at_start: int = 0,
    poll_period: float = 0.0,
    under_way_at_start: int = 0,
) -> PlanReport:
    """The report of ``orders`` played from ``start`` in ``journal`` (see module docstring)."""
    machines = machines_of(config)
    span = max(ended, start + 1e-9)
    figures = shift_report(journal, machines, {}, start, span)
    busy = _busy_while_up(journal, machines, start, span)
    parts = [p for p in journal.parts() if p.status == "done" and start <= p.updated <= until]
    steps = within(journal.steps(), start, until)
    alarms = [a for a in journal.alarms() if start <= a.raised <= until]
    types = {p.id: p.part_type for p in journal.parts()}
    return PlanReport(
        cell=config.name,
        policy=policy,
        seed=seed,
        poll_period=poll_period,
        start=start,
        until=until,
        ended=ended,
        wall_s=wall_s,
        orders=[_outcome(o, journal, ended, until) for o in orders],
        parts_made=dict(Counter(p.part_type for p in parts)),
        utilization={m: round(b / (span - start), 4) for m, b in busy.items()},
        busy_s={m: round(b, 3) for m, b in busy.items()},
        down_s={m.machine: m.down_s for m in figures.machines},
        faults=list(faults),
        alarms_raised=len(alarms),
        alarms=[
            {"machine": a.machine, "code": a.code, "text": a.text, "raised": a.raised}
            for a in sorted(alarms, key=lambda a: (a.raised, a.id))
        ],
        steps_failed=sum(s.state in ("failed", "interrupted") for s in steps),
        held_at_start=held_at_start,
        under_way_at_start=under_way_at_start,
        steps=[_step(s, types) for s in steps],
    )


def _busy_while_up(
    journal: Journal, machines: Sequence[str], start: float, end: float
) -> dict[str, float]:
    """Each machine's time in steps over ``[start, end]`` while it was not down (out of
    service, or alarmed: the shift report's down intervals, the cell's alarms counted on
    every machine), s. A step's time counts as the shift report counts it (an interrupted
    one none, one in flight up to ``end``). The shift report's own down intervals and their
    union: one definition of "down" for its ``down_s`` and this."""
    downs = _down_intervals(journal, journal.alarms(), end)
    steps = [s for s in journal.steps() if s.state != "interrupted"]
    out: dict[str, float] = {}
    for name in machines:
        down = [(t0, t1) for t0, t1, _ in downs.get(name, []) + downs.get("cell", [])]
        busy = [
            (s.started, s.ended if s.ended is not None else end) for s in steps if s.machine == name
        ]
        # Busy or down, less down: the time busy and not down.
        out[name] = max(0.0, _union(busy + down, start, end) - _union(down, start, end))
    return out


def _step(step: Step, types: dict[str, str]) -> dict[str, Any]:
    return {
        "part_id": step.part_id,
        "part_type": types.get(step.part_id, ""),
        "kind": step.kind,
        "machine": step.machine,
        "program": step.program,
        "state": step.state,
        "started": step.started,
        "ended": step.ended,
    }


def _tick(start: float, span: float) -> Any:
    """Axis labels as wall-clock times (with the day when the plan spans days)."""
    fmt = "%a %H:%M" if span > 20 * 3600 else "%H:%M:%S" if span < 600 else "%H:%M"

    def label(offset: float) -> str:
        from datetime import datetime

        return datetime.fromtimestamp(start + offset).strftime(fmt)

    return label


def _window_rows(fault: FaultWindow, machines: Sequence[str]) -> list[tuple[str, str]]:
    """The chart's rows a fault window is shaded on, each with its label: its machine's, or
    every row for the PLC's (it has no row: an emergency stop, a dropped or silent PLC
    stops the whole cell)."""
    what = fault.fault + (f"={fault.arg}" if fault.arg else "")
    if fault.machine == PLC:
        return [(row, f"{PLC} {what} (the whole cell)") for row in machines]
    return [(fault.machine, fault.fault)]


def plan_svg(
    reports: Sequence[PlanReport],
    steps: Sequence[Sequence[Step]],
    part_types: Sequence[dict[str, str]],
    machines: list[str],
) -> str:
    """The Gantt chart of one plan, or of several (one per policy) on one time axis: the
    demo's chart, its axis in wall-clock time from the plan's start to its end, each fault
    window shaded on its machine's row (a PLC's, which stops the whole cell, on every row)
    up to the plan's end, as its steps are."""
    runs = []
    for report, found, types in zip(reports, steps, part_types, strict=True):
        windows = [
            # A window that ends after the plan is drawn to the axis' end, not past it.
            GanttWindow(
                row, f.start, report.until if f.end is None else min(f.end, report.until), label
            )
            for f in report.faults
            for row, label in _window_rows(f, machines)
        ]
        title = f"policy {policy_name(report.policy)}: on time {report.on_time}, late {report.late}"
        runs.append(GanttRun(title, within(found, report.start, report.until), types, report.start))
        runs[-1].windows.extend(windows)
    span = max(r.until - r.start for r in reports)
    return gantt_runs_svg(runs, machines, span=span, tick=_tick(reports[0].start, span))
