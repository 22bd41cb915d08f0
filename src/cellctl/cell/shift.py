"""A shift's figures from the journal: OEE per machine after ISO 22400, parts, alarms, downtime.

::

    ideal = ideal_times(config)                        # each step's time on the machines' models
    report = shift_report(journal, ["robot", "cnc1", "cnc2"], ideal, start, end)
    report.machines[0].oee                             # availability x performance x quality

Every figure is read from the journal over the window ``[start, end]`` (docs/cell.md,
"The shift report", states the same definitions for the shift lead):

- **Planned busy time** (PBT, ISO 22400-2): the window. No planned stop is journaled, so the
  whole window counts as planned.
- **Actual production time** (APT): the time the machine spent in steps (a transfer, a cut),
  clipped to the window; a step still in flight counts up to the window's end.
- **Availability** = APT / PBT.
- **Performance** (ISO 22400's effectiveness, PRI x PQ / APT): the ideal time of the steps
  the machine finished, over APT. A step's ideal time is what the machine's own model says it
  takes (:func:`ideal_times`: the robot program's motion and interlocks, the mill program's
  door, download and cut from its toolpath), at the cell's time scale; a step with no ideal
  time counts its own duration.
- **Quality** = good quantity / produced quantity: the steps that ended on the machine in the
  window (finished, failed, interrupted), of which the good ones finished and their part is
  neither held nor scrapped now.
- **OEE** = availability x performance x quality.
- **Down time** (ADOT): the union of the times the machine was out of service (the journal's
  service log) or had an alarm of its own or the cell's active: each of the alarm's spells
  (:meth:`~cellctl.cell.journal.Journal.alarm_spells`), from raised or active again until it
  returned to normal, else until it was cleared. An alarm whose condition went and came
  back counts the times it was active, not the time between. **Downtime by reason** counts
  each reason's time apart (the union of its own intervals: two alarms of one code at once
  count once, two reasons at once each count), so its total may pass the machine's down
  time.
- **Parts**: good (done), held (held now) and scrapped, by when they last changed.
- **Alarms by cause**: the alarms raised in the window by code, with their priority.

A ratio whose denominator is 0 is not known yet: None, not 0 (nothing went wrong). Quality
while no step ended in the window, performance while the machine spent no time in steps, and
OEE while either is not known.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from cellctl.cell.causes import ESTOP
from cellctl.cell.config import CellConfig
from cellctl.cell.journal import Alarm, Journal, Step

#: The longest window a report covers, s (a week: the API refuses more).
MAX_WINDOW = 7 * 24 * 3600.0
#: The default window: one shift before its end, s.
SHIFT = 8 * 3600.0


@dataclass(frozen=True)
class MachineFigures:
    """One machine's figures over the window (times in s, ratios 0 to 1; None: not known
    yet, its denominator 0)."""

    machine: str
    planned_s: float
    production_s: float
    ideal_s: float
    down_s: float
    steps_ended: int
    steps_good: int
    availability: float
    performance: float | None
    quality: float | None
    oee: float | None


@dataclass
class ShiftReport:
    """The figures of one window of the journal (:func:`shift_report`)."""

    start: float
    end: float
    time_scale: float
    machines: list[MachineFigures]
    parts_good: int
    parts_held: int
    parts_scrapped: int
    alarms_by_cause: list[dict[str, Any]] = field(default_factory=list)
    downtime_by_reason: list[dict[str, Any]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """The report as JSON-ready data (the API's ``report.shift`` answer)."""
        return asdict(self)


def ideal_times(config: CellConfig, time_scale: float | None = None) -> dict[str, float]:
    """Each step's ideal seconds by ``machine/program`` (the journal's machine and program):
    from the machines' own models (:mod:`cellctl.cell.physics`) at ``time_scale`` (default:
    ``[cell] time_scale``, 1 for a real cell)."""
    from cellctl.cell.physics import physical_durations

    scale = cell_time_scale(config) if time_scale is None else time_scale
    phys = physical_durations(config, time_scale=scale)
    robot = config.robot.name
    out = {f"{robot}/{name}": t.seconds for name, t in phys.transfers.items()}
    out.update({f"{mill}/{step}": t.seconds for (mill, step), t in phys.machining.items()})
    return out


def cell_time_scale(config: CellConfig) -> float:
    """``[cell] time_scale``: how many times faster than a real cell the machines run."""
    return time_scale_of(config.raw)


def time_scale_of(raw: Mapping[str, Any]) -> float:
    """:func:`cell_time_scale` of a cell.toml's contents as read (``tomllib.loads``)."""
    return float(raw.get("cell", {}).get("time_scale", 1.0))


def shift_report(
    journal: Journal,
    machines: Iterable[str],
    ideal: Mapping[str, float],
    start: float,
    end: float,
    *,
    time_scale: float = 1.0,
) -> ShiftReport:
    """The figures of ``machines`` over ``[start, end]`` (module docstring); ``ideal``:
    :func:`ideal_times`."""
    if end <= start:
        raise ValueError(f"the window ends ({end}) before it starts ({start})")
    steps = journal.steps()
    alarms = journal.alarms()
    downs = _down_intervals(journal, alarms, end)
    bad = {p.id for p in journal.parts(["held", "scrapped"])}
    figures = [
        _machine(name, steps, ideal, downs.get(name, []) + downs.get("cell", []), bad, start, end)
        for name in machines
    ]
    parts = [p for p in journal.parts() if start <= p.updated <= end]
    raised = [a for a in alarms if start <= a.raised <= end]
    causes = Counter((a.code, a.priority) for a in raised)
    where: dict[str, set[str]] = defaultdict(set)
    for a in raised:
        where[a.code].add(a.machine)
    reasons: dict[tuple[str, str], list[tuple[float, float]]] = defaultdict(list)
    for machine, intervals in downs.items():
        for t0, t1, reason in intervals:
            reasons[(machine, reason)].append((t0, t1))
    by_reason = {key: _union(spans, start, end) for key, spans in reasons.items()}
    return ShiftReport(
        start=start,
        end=end,
        time_scale=time_scale,
        machines=figures,
        parts_good=sum(p.status == "done" for p in parts),
        parts_held=sum(p.status == "held" for p in parts),
        parts_scrapped=sum(p.status == "scrapped" for p in parts),
        alarms_by_cause=[
            {"code": code, "priority": pri, "count": n, "machines": sorted(where[code])}
            for (code, pri), n in sorted(causes.items(), key=lambda kv: (-kv[1], kv[0]))
        ],
        downtime_by_reason=[
            {"machine": m, "reason": r, "seconds": round(s, 3)}
            for (m, r), s in sorted(by_reason.items(), key=lambda kv: -kv[1])
            if s > 0
        ],
    )


def _machine(
    name: str,
    steps: list[Step],
    ideal: Mapping[str, float],
    downs: list[tuple[float, float, str]],
    held: set[str],
    start: float,
    end: float,
) -> MachineFigures:
    planned = end - start
    production = ideal_s = 0.0
    ended = good = 0
    for s in steps:
        if s.machine != name:
            continue
        if s.state != "interrupted":  # its end is not known: it counts no time
            production += _overlap(s.started, s.ended if s.ended is not None else end, start, end)
        if s.ended is None or not start <= s.ended <= end:
            continue
        ended += 1
        if s.state == "finished":
            ideal_s += ideal.get(f"{name}/{s.program}", s.ended - s.started)
            good += s.part_id not in held
    down = _union([(t0, t1) for t0, t1, _ in downs], start, end)
    availability = production / planned
    # Nothing to divide by: not known yet (a 0 would read as a machine that did badly).
    performance = ideal_s / production if production > 0 else None
    quality = good / ended if ended else None
    oee = None if performance is None or quality is None else availability * performance * quality
    return MachineFigures(
        machine=name,
        planned_s=round(planned, 3),
        production_s=round(production, 3),
        ideal_s=round(ideal_s, 3),
        down_s=round(down, 3),
        steps_ended=ended,
        steps_good=good,
        availability=round(availability, 4),
        performance=_rounded(performance),
        quality=_rounded(quality),
        oee=_rounded(oee),
    )


def _rounded(ratio: float | None) -> float | None:
    return None if ratio is None else round(ratio, 4)


#: Alarms of one machine that stop the whole cell: down for every machine, as the cell's own
#: alarms are (the PLC's emergency stop input: no machine may move while it is pressed).
CELL_WIDE = {(ESTOP.machine, ESTOP.code)}
#: Alarms of one machine that hold every transfer until they are cleared (a door or vise the
#: PLC did not move: docs/cell.md): down for the robot.
TRANSFERS_HELD = {("plc", "interlock")}


def _down_intervals(
    journal: Journal, alarms: list[Alarm], end: float
) -> dict[str, list[tuple[float, float, str]]]:
    """Each machine's down intervals with their reason: the spells its alarms were active
    (one still active: to ``end``) and its time out of service. The one reading of "down"
    for every figure built on it (this report, a plan's report)."""
    out: dict[str, list[tuple[float, float, str]]] = defaultdict(list)
    spells = journal.alarm_spells(alarms)
    # The robots: the machines that carried parts (an alarm that holds transfers is theirs).
    robots = {step.machine for step in journal.steps() if step.kind == "transfer"}
    for a in alarms:
        for began, ended in spells[a.id]:
            stop = end if ended is None else min(ended, end)
            out[a.machine].append((began, max(began, stop), f"alarm: {a.code}"))
            if (a.machine, a.code) in CELL_WIDE:
                out["cell"].append((began, max(began, stop), f"alarm: {a.machine} {a.code}"))
            if (a.machine, a.code) in TRANSFERS_HELD:
                for robot in robots:
                    why = f"alarm: {a.machine} {a.code} (transfers held)"
                    out[robot].append((began, max(began, stop), why))
    since: dict[str, tuple[float, str]] = {}
    for t, name, in_service, reason in journal.service_log():
        if not in_service and name not in since:
            since[name] = (t, reason)
        elif in_service and name in since:
            t0, why = since.pop(name)
            out[name].append((t0, t, f"out of service: {why}"))
    for name, (t0, why) in since.items():
        out[name].append((t0, max(t0, end), f"out of service: {why}"))
    return out


def _overlap(t0: float, t1: float, start: float, end: float) -> float:
    return max(0.0, min(t1, end) - max(t0, start))


def _union(intervals: list[tuple[float, float]], start: float, end: float) -> float:
    """The length of the union of ``intervals`` inside ``[start, end]``."""
    total, reach = 0.0, start
    for t0, t1 in sorted((max(a, start), min(b, end)) for a, b in intervals):
        if t1 <= reach or t1 <= t0:  # before what is counted, or outside the window
            continue
        total += t1 - max(t0, reach)
        reach = t1
    return total
