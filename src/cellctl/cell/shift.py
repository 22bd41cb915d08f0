"""A shift's figures from the journal: OEE per machine after ISO 22400, parts, alarms, downtime.

::

    ideal = ideal_times(config)                        # each step's time on the machines' models
    report = shift_report(journal, ["robot", "cnc1", "cnc2"], ideal, start, end)
    report.machines[0].oee                             # availability x performance x quality

Every figure is read from the journal over the window ``[start, end]`` (docs/cell.md,
"The shift report", states the same definitions for the shift lead):

- **Planned busy time** (PBT, ISO 22400-2): the window. No planned stop is journaled, so the
  whole window counts as planned.
- **Actual production time** (APT, OEE's run time: producing or trying to): the time the
  machine spent in steps (a transfer, a cut), clipped to the window; a step still in flight
  counts up to the window's end. A failed step counts only its time while the machine was
  not down: tried while the cell was stopped (the PLC not answering, an E-stop) or the
  machine alarmed, it is down time (an availability loss), never both. Its time up stays in
  APT and earns no ideal time: a performance loss, shown apart as ``failed_s`` (and
  ``steps_failed``, the failed steps that ended in the window).
- **Availability** = APT / PBT.
- **Performance** (ISO 22400's effectiveness, PRI x PQ / APT): the ideal time of the steps
  the machine finished, over APT. A step's ideal time is what the machine's own model says it
  takes (:func:`ideal_times`: the robot program's motion and interlocks, the mill program's
  door, download and cut from its toolpath), at the cell's time scale; a step with no ideal
  time counts its own duration.
- **Quality** = good quantity / produced quantity, counted in parts (a part once, however
  many of its steps the machine ran): the parts the machine worked on (a step of theirs ran
  on it) that were finished or scrapped in the window, of which the finished ones are good.
  A part neither finished nor scrapped yet (waiting, held) counts in neither. The steps stay
  beside it: ``steps_ended`` (finished, failed, interrupted in the window) and ``steps_good``
  (finished, their part neither held nor scrapped now).
- **OEE** = availability x performance x quality.
- **Down time** (ADOT): the union of the times the machine was out of service (the journal's
  service log) or had an alarm of its own or the cell's active (:data:`CELL_WIDE`: the PLC's
  emergency stop, the PLC not answering; counted once where the machine's own alarm
  overlaps them): each of the alarm's spells
  (:meth:`~cellctl.cell.journal.Journal.alarm_spells`), from raised or active again until it
  returned to normal, else until it was cleared. An alarm whose condition went and came
  back counts the times it was active, not the time between. **Downtime by reason** counts
  each reason's time apart (the union of its own intervals: two alarms of one code at once
  count once, two reasons at once each count), so its total may pass the machine's down
  time.
- **Parts**: good (done), held (held now) and scrapped, by when they last changed.
- **Alarms by cause**: the alarms raised in the window by code, with their priority and how
  many on each machine.
- **The controller**: the window's time split into running, paused, stopped and not known
  (they add up to the window), from the journal's controller log (started, paused, resumed,
  stopped, by whom and why). A controller that started again with no "stopped" before (a
  crash, a kill) ran until it was last heard of (a step of its began or ended, it raised an
  alarm), then "ended unheard": not known until the next start. So did the last one when no
  controller runs now (``running_now=False``). Before the log's first event: not known.
- **At the window's end** (the handover): the parts held then (held now, since at or before
  the end: the journal keeps a part's present state, so a part held then and released
  since is not listed) and the alarms open then (raised by the end, not cleared by it), each
  acknowledged by then or not, its condition still active then or returned to normal.

A ratio whose denominator is 0 is not known yet: None, not 0 (nothing went wrong). Quality
while no part the machine worked on was finished or scrapped in the window, performance
while the machine spent no time in steps, and OEE while either is not known.
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
    #: Of ``production_s``, the failed steps' (outside down time): run time that made nothing.
    failed_s: float
    steps_ended: int
    steps_good: int
    #: Of ``steps_ended``, the failed ones.
    steps_failed: int
    parts_ended: int
    parts_good: int
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
    #: The window's time by the controller's state, s (they add up to the window).
    running_s: float = 0.0
    paused_s: float = 0.0
    stopped_s: float = 0.0
    not_known_s: float = 0.0
    #: The controller's events in the window: ``time``, ``event``, ``by``, ``why``.
    controller_events: list[dict[str, Any]] = field(default_factory=list)
    #: The parts held at the window's end: ``part``, ``order``, ``part_type``, ``location``,
    #: ``since``, ``why``.
    held_at_end: list[dict[str, Any]] = field(default_factory=list)
    #: The alarms open at the window's end: ``id``, ``machine``, ``code``, ``priority``,
    #: ``text``, ``raised``, ``acknowledged``, ``acked_by``, ``active``.
    open_alarms_at_end: list[dict[str, Any]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not (self.running_s or self.paused_s or self.stopped_s or self.not_known_s):
            # Nothing recorded (no journal yet): the window is not known, not "running".
            self.not_known_s = round(self.end - self.start, 3)

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
    running_now: bool = True,
) -> ShiftReport:
    """The figures of ``machines`` over ``[start, end]`` (module docstring); ``ideal``:
    :func:`ideal_times`; ``running_now``: whether a controller runs now (the API's own)."""
    if end <= start:
        raise ValueError(f"the window ends ({end}) before it starts ({start})")
    steps = journal.steps()
    alarms = journal.alarms()
    downs = _down_intervals(journal, alarms, end)
    all_parts = journal.parts()
    bad = {p.id for p in all_parts if p.status in ("held", "scrapped")}
    # Finished or scrapped in the window: the parts quality counts (True: good).
    ended = {
        p.id: p.status == "done"
        for p in all_parts
        if p.status in ("done", "scrapped") and start <= p.updated <= end
    }
    figures = [
        _machine(
            name,
            steps,
            ideal,
            downs.get(name, []) + downs.get("cell", []),
            bad,
            ended,
            start,
            end,
        )
        for name in machines
    ]
    parts = [p for p in all_parts if start <= p.updated <= end]
    raised = [a for a in alarms if start <= a.raised <= end]
    causes = Counter((a.code, a.priority) for a in raised)
    where: dict[str, Counter[str]] = defaultdict(Counter)
    for a in raised:
        where[a.code][a.machine] += 1
    reasons: dict[tuple[str, str], list[tuple[float, float]]] = defaultdict(list)
    for machine, intervals in downs.items():
        for t0, t1, reason in intervals:
            reasons[(machine, reason)].append((t0, t1))
    by_reason = {key: _union(spans, start, end) for key, spans in reasons.items()}
    split, events = _controller_time(journal, steps, alarms, start, end, running_now)
    return ShiftReport(
        start=start,
        end=end,
        time_scale=time_scale,
        machines=figures,
        parts_good=sum(p.status == "done" for p in parts),
        parts_held=sum(p.status == "held" for p in parts),
        parts_scrapped=sum(p.status == "scrapped" for p in parts),
        alarms_by_cause=[
            {
                "code": code,
                "priority": pri,
                "count": n,
                "machines": sorted(where[code]),
                "by_machine": dict(sorted(where[code].items())),
            }
            for (code, pri), n in sorted(causes.items(), key=lambda kv: (-kv[1], kv[0]))
        ],
        downtime_by_reason=[
            {"machine": m, "reason": r, "seconds": round(s, 3)}
            for (m, r), s in sorted(by_reason.items(), key=lambda kv: -kv[1])
            if s > 0
        ],
        running_s=split["running"],
        paused_s=split["paused"],
        stopped_s=split["stopped"],
        not_known_s=split["not_known"],
        controller_events=events,
        held_at_end=[
            {
                "part": p.id,
                "order": p.order_id,
                "part_type": p.part_type,
                "location": p.location,
                "since": p.updated,
                "why": p.note,
            }
            for p in all_parts
            if p.status == "held" and p.updated <= end
        ],
        open_alarms_at_end=_open_at(journal, alarms, end),
    )


def _machine(
    name: str,
    steps: list[Step],
    ideal: Mapping[str, float],
    downs: list[tuple[float, float, str]],
    held: set[str],
    parts_ended: Mapping[str, bool],
    start: float,
    end: float,
) -> MachineFigures:
    planned = end - start
    production = ideal_s = failed_s = 0.0
    ended = good = failed = 0
    worked: set[str] = set()  # the parts it ran a step of
    down_spans = [(t0, t1) for t0, t1, _ in downs]
    for s in steps:
        if s.machine != name:
            continue
        worked.add(s.part_id)
        if s.state != "interrupted":  # its end is not known: it counts no time
            stop = s.ended if s.ended is not None else end
            run = _overlap(s.started, stop, start, end)
            if s.state == "failed":
                # A step tried while the machine was down (the cell stopped, its alarm
                # active) made nothing because of that stop: the stop's loss, counted in
                # down time, not run time too. A finished step keeps all its time: it made
                # its part, and its ideal time is earned against it.
                run -= _union(down_spans, max(s.started, start), min(stop, end))
                failed_s += run
            production += run
        if s.ended is None or not start <= s.ended <= end:
            continue
        ended += 1
        failed += s.state == "failed"
        if s.state == "finished":
            ideal_s += ideal.get(f"{name}/{s.program}", s.ended - s.started)
            good += s.part_id not in held
    down = _union(down_spans, start, end)
    availability = production / planned
    produced = [parts_ended[p] for p in worked if p in parts_ended]
    # Nothing to divide by: not known yet (a 0 would read as a machine that did badly).
    performance = ideal_s / production if production > 0 else None
    quality = sum(produced) / len(produced) if produced else None
    oee = None if performance is None or quality is None else availability * performance * quality
    return MachineFigures(
        machine=name,
        planned_s=round(planned, 3),
        production_s=round(production, 3),
        ideal_s=round(ideal_s, 3),
        down_s=round(down, 3),
        failed_s=round(failed_s, 3),
        steps_ended=ended,
        steps_good=good,
        steps_failed=failed,
        parts_ended=len(produced),
        parts_good=sum(produced),
        availability=round(availability, 4),
        performance=_rounded(performance),
        quality=_rounded(quality),
        oee=_rounded(oee),
    )


def _rounded(ratio: float | None) -> float | None:
    return None if ratio is None else round(ratio, 4)


#: Alarms of one machine that stop the whole cell: down for every machine, as the cell's own
#: alarms are. The PLC's emergency stop input: no machine may move while it is pressed. The
#: PLC not answering (its link alarm: silent, late past its deadline, closed): no door or
#: vise moves and the stop cannot be read, so no transfer or cut can start meanwhile.
CELL_WIDE = {(ESTOP.machine, ESTOP.code), (ESTOP.machine, "link")}
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


#: The controller's state after each event of its log.
_AFTER = {"started": "running", "resumed": "running", "paused": "paused", "stopped": "stopped"}
#: The event a report adds where a controller ended without a word (module docstring).
ENDED_UNHEARD = "ended unheard"


def _controller_time(
    journal: Journal,
    steps: list[Step],
    alarms: list[Alarm],
    start: float,
    end: float,
    running_now: bool,
) -> tuple[dict[str, float], list[dict[str, Any]]]:
    """The window's seconds by the controller's state, and its events in the window (with
    the "ended unheard" the report reads from the journal: module docstring)."""
    # When the controller was last heard of: what only a running controller journals.
    heard = sorted(
        {s.started for s in steps}
        | {s.ended for s in steps if s.ended is not None}
        | {a.raised for a in alarms}
    )

    def gone_after(since: float, before: float) -> float:
        return max([since, *(t for t in heard if since <= t <= before)])

    spans: list[tuple[float, float, str]] = []
    events: list[tuple[float, str, str, str]] = []
    state, since = "not_known", float("-inf")
    for t, event, by, why in journal.controller_log():
        if event == "started" and state in ("running", "paused"):
            gone = gone_after(since, t)
            spans.append((since, gone, state))
            events.append((gone, ENDED_UNHEARD, "", ""))
            state, since = "not_known", gone
        spans.append((since, t, state))
        events.append((t, event, by, why))
        state, since = _AFTER.get(event, state), t
    if not running_now and state in ("running", "paused"):
        gone = gone_after(since, float("inf"))
        spans.append((since, gone, state))
        events.append((gone, ENDED_UNHEARD, "", ""))
        state, since = "not_known", gone
    spans.append((since, max(since, end), state))
    split = dict.fromkeys(("running", "paused", "stopped", "not_known"), 0.0)
    for t0, t1, what in spans:
        split[what] += _overlap(t0, t1, start, end)
    return (
        {k: round(v, 3) for k, v in split.items()},
        [
            {"time": t, "event": e, "by": by, "why": why}
            for t, e, by, why in events
            if start <= t <= end
        ],
    )


def _open_at(journal: Journal, alarms: list[Alarm], end: float) -> list[dict[str, Any]]:
    """The alarms open at ``end``: raised by then, not cleared by then."""
    found = [a for a in alarms if a.raised <= end and (a.cleared is None or a.cleared > end)]
    spells = journal.alarm_spells(found)
    out = []
    for a in found:
        acked = a.acked is not None and a.acked <= end
        out.append(
            {
                "id": a.id,
                "machine": a.machine,
                "code": a.code,
                "priority": a.priority,
                "text": a.text,
                "raised": a.raised,
                "acknowledged": acked,
                "acked_by": a.acked_by if acked else "",
                # Its condition at the end: in one of its spells (active), else returned.
                "active": any(b <= end and (e is None or e > end) for b, e in spells[a.id]),
            }
        )
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
