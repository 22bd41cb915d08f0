"""``cellctl report shift``: the figures a shift lead reads, from the journal.

::

    cellctl report shift                                # the last 8 h, a table at 80 columns
    cellctl report shift --from 2026-11-25T06:00 --to 2026-11-25T14:00 --csv shift.csv
    cellctl report shift --from 22:00 --to 06:00        # last night's (HH:MM: the last such)
    cellctl report shift --html shift.html --json

The figures (availability, performance, quality and OEE per machine after ISO 22400, parts,
alarms by cause, downtime by reason, the controller's running, paused and stopped time, and
what is left at the window's end: parts held, alarms open) and their definitions are
:mod:`cellctl.cell.shift`'s; they come through the control API's ``report.shift``, so the
dashboard's Shift panel shows the same numbers.
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Callable
from datetime import datetime, timedelta
from html import escape
from pathlib import Path
from typing import Any

import click

from cellctl.cell.journal import Step
from cellctl.cell.report import gantt_svg
from cellctl.cell.shift import ENDED_UNHEARD
from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.files import write_output
from cellctl.ui.calls import cell_call
from cellctl.ui.common import console, json_option, print_json, print_line, run

#: The table's width: it fits an 80-column terminal.
WIDTH = 80


def _when(t: float) -> str:
    return datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S")


def _hms(seconds: float) -> str:
    if seconds < 60:  # an emulated cell's short runs: tenths still say something
        return f"{seconds:.1f} s"
    s = round(seconds)
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


#: A ratio not known yet (its denominator 0: no part ended, no time in steps).
NOT_KNOWN = "—"


def _pct(x: float | None) -> str:
    return NOT_KNOWN if x is None else f"{100 * x:5.1f} %"


def _clip(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 1] + "…"


def shift_lines(report: dict[str, Any], cell: str = "") -> list[str]:
    """The report as lines of at most :data:`WIDTH` characters."""
    head = f"Shift report{' of ' + cell if cell else ''}"
    out = [
        _clip(head, WIDTH),
        f"{_when(report['start'])} to {_when(report['end'])} "
        f"({_hms(report['end'] - report['start'])}, time scale {report['time_scale']:g})",
        "",
        f"{'machine':<10} {'avail':>7} {'perf':>7} {'quality':>7} {'OEE':>7} "
        f"{'producing':>10} {'down':>9} {'steps':>6} {'parts':>6}",
    ]
    for m in report["machines"]:
        out.append(
            f"{_clip(m['machine'], 10):<10} {_pct(m['availability']):>7} "
            f"{_pct(m['performance']):>7} {_pct(m['quality']):>7} {_pct(m['oee']):>7} "
            f"{_hms(m['production_s']):>10} {_hms(m['down_s']):>9} "
            f"{m['steps_good']:>3}/{m['steps_ended']:<2} {m['parts_good']:>3}/{m['parts_ended']:<2}"
        )
    failed = [m for m in report["machines"] if m["steps_failed"] or m["failed_s"] > 0]
    if failed:
        # Their time while the machine was down is in its down time, not here too.
        out.append("failed steps, their run time (a performance loss):")
    for m in failed:
        out.append(_clip(f"  {_clip(m['machine'], 10):<10} {_failed(m)}", WIDTH))
    out += [
        "",
        f"parts good {report['parts_good']}, held {report['parts_held']}, "
        f"scrapped {report['parts_scrapped']}",
        "",
        "alarms by cause:" + ("" if report["alarms_by_cause"] else " none"),
    ]
    for a in report["alarms_by_cause"]:
        machines = ", ".join(a["machines"])
        out.append(_clip(f"  {a['count']:>4} x {a['code']:<16} {a['priority']:<7} {machines}", 80))
    out.append("downtime by reason:" + ("" if report["downtime_by_reason"] else " none"))
    for d in report["downtime_by_reason"]:
        out.append(_clip(f"  {_hms(d['seconds']):>9}  {d['machine']:<8} {d['reason']}", WIDTH))
    return [*out, "", *_controller_lines(report), "", *_handover_lines(report)]


def _failed(machine: dict[str, Any]) -> str:
    """A machine's failed steps and their run time: ``8 steps, 15.0 s``."""
    return f"{_count(machine['steps_failed'], 'step')}, {_hms(machine['failed_s'])}"


#: The controller's states, as the table names them, and their keys in the report.
_STATES = (("running", "running_s"), ("paused", "paused_s"), ("stopped", "stopped_s"),
           ("not known", "not_known_s"))  # fmt: skip
#: The controller's events the table lists at most (the latest; --json and --csv list all).
EVENT_LINES = 12


def _controller_lines(report: dict[str, Any]) -> list[str]:
    """The window's time by the controller's state (it adds up), and its events."""
    split = ", ".join(
        f"{name} {_hms(report[key])}"
        for name, key in _STATES
        if key != "not_known_s" or report[key] > 0  # none: said only when there is some
    )
    out = [_clip(f"controller: {split}", WIDTH)]
    events = report["controller_events"]
    if len(events) > EVENT_LINES:
        out.append(f"  ({len(events) - EVENT_LINES} earlier events: --json and --csv list them)")
    for e in events[-EVENT_LINES:]:
        out.append(_clip(f"  {_short(e['time'])}  {event_words(e)}", WIDTH))
    return out


def event_words(event: dict[str, Any]) -> str:
    """A controller event in words: ``resumed by token:eve (engineer)``, ``paused:
    emergency stop pressed``."""
    if event["event"] == ENDED_UNHEARD:
        return "ended without stopping (a crash, a kill?): last heard of then"
    by = f" by {event['by']}" if event["by"] else ""
    why = f": {event['why']}" if event["why"] else ""
    return f"{event['event']}{by}{why}"


def _handover_lines(report: dict[str, Any]) -> list[str]:
    """What the window leaves to the next shift: parts held, alarms open, at its end."""
    held, alarms = report["held_at_end"], report["open_alarms_at_end"]
    unacked = sum(not a["acknowledged"] for a in alarms)
    parts = f"{_count(len(held), 'part')} held"
    opened = f"{_count(len(alarms), 'alarm')} open"
    if alarms:
        opened += f" ({unacked} not acknowledged)" if unacked else " (all acknowledged)"
    out = [f"at the window's end: {parts}, {opened}"]
    for p in held:
        out.append(
            _clip(
                f"  {p['part']:<8} {p['part_type']:<10} at {p['location']:<8} "
                f"since {_short(p['since'])}  {p['why']}",
                WIDTH,
            )
        )
    for a in alarms:
        # Two lines: what it is, then where it stands (neither cut off by a long text).
        out.append(
            _clip(
                f"  alarm {a['id']} {a['machine']} {a['code']} ({a['priority']}) since "
                f"{_short(a['raised'])}: {a['text']}",
                WIDTH,
            )
        )
        out.append(_clip(f"    {alarm_standing(a)}", WIDTH))
    return out


def alarm_standing(alarm: dict[str, Any]) -> str:
    """Where an alarm open at the window's end stood then, in words: ``still active, not
    acknowledged``, ``returned to normal, acknowledged by token:olga``."""
    condition = "still active" if alarm["active"] else "returned to normal"
    if not alarm["acknowledged"]:
        return f"{condition}, not acknowledged"
    return f"{condition}, acknowledged" + (f" by {alarm['acked_by']}" if alarm["acked_by"] else "")


def _count(n: int, thing: str) -> str:
    return f"no {thing}" if n == 0 else f"{n} {thing}" + ("s" if n > 1 else "")


def _short(t: float) -> str:
    return datetime.fromtimestamp(t).strftime("%m-%d %H:%M:%S")


def shift_csv(report: dict[str, Any]) -> str:
    """The report as CSV: one row per figure, ``section,name,field,value,machine`` (a ratio
    not known yet has an empty value; ``machine``: the machine the row is about, if one)."""
    buffer = io.StringIO()
    out = csv.writer(buffer, lineterminator="\n")
    out.writerow(["section", "name", "field", "value", "machine"])
    out.writerow(["window", "", "start", _when(report["start"]), ""])
    out.writerow(["window", "", "end", _when(report["end"]), ""])
    out.writerow(["window", "", "time_scale", report["time_scale"], ""])
    for m in report["machines"]:
        for key, value in m.items():
            if key != "machine":
                out.writerow(["machine", m["machine"], key, value, m["machine"]])
    for key in ("parts_good", "parts_held", "parts_scrapped"):
        out.writerow(["parts", "", key.removeprefix("parts_"), report[key], ""])
    for a in report["alarms_by_cause"]:
        # One row per machine the cause was raised on: its count there (they add up).
        for machine, n in a["by_machine"].items():
            out.writerow(["alarms", a["code"], "count", n, machine])
            out.writerow(["alarms", a["code"], "priority", a["priority"], machine])
    for d in report["downtime_by_reason"]:
        out.writerow(["downtime", d["machine"], d["reason"], d["seconds"], d["machine"]])
    for key in ("running_s", "paused_s", "stopped_s", "not_known_s"):
        out.writerow(["controller", "", key, report[key], ""])
    for i, e in enumerate(report["controller_events"], 1):
        for key, value in (("time", _when(e["time"])), ("event", e["event"]),
                           ("by", e["by"]), ("why", e["why"])):  # fmt: skip
            out.writerow(["controller_event", i, key, value, ""])
    machines = {m["machine"] for m in report["machines"]}
    for p in report["held_at_end"]:
        where = p["location"] if p["location"] in machines else ""
        for key in ("order", "part_type", "location", "since", "why"):
            value = _when(p[key]) if key == "since" else p[key]
            out.writerow(["held_at_end", p["part"], key, value, where])
    for a in report["open_alarms_at_end"]:
        for key in ("code", "priority", "raised", "acknowledged", "acked_by", "active", "text"):
            value = a[key]
            if key == "raised":
                value = _when(value)
            elif isinstance(value, bool):
                value = "yes" if value else "no"
            out.writerow(["open_alarm_at_end", a["id"], key, value, a["machine"]])
    return buffer.getvalue()


def shift_html(report: dict[str, Any], steps: list[dict[str, Any]], cell: str = "") -> str:
    """One page: the figures' tables and the window's Gantt chart (the demo's)."""
    fields = {f for f in Step.__dataclass_fields__}
    found = [Step(**{k: v for k, v in s.items() if k in fields}) for s in steps]
    types = {s["part_id"]: s.get("part_type", "") for s in steps}
    machines = [m["machine"] for m in report["machines"]]
    svg = gantt_svg(
        [s for s in found if s.started <= report["end"]],
        machines,
        part_types=types,
        since=report["start"],
        title="steps in the window",
    )
    rows = "".join(
        f"<tr><td>{escape(m['machine'])}</td><td>{_pct(m['availability'])}</td>"
        f"<td>{_pct(m['performance'])}</td><td>{_pct(m['quality'])}</td>"
        f"<td><b>{_pct(m['oee'])}</b></td><td>{_hms(m['production_s'])}</td>"
        f"<td>{_hms(m['down_s'])}</td><td>{m['steps_good']} / {m['steps_ended']}</td>"
        f"<td>{_failed(m)}</td>"
        f"<td>{m['parts_good']} / {m['parts_ended']}</td></tr>"
        for m in report["machines"]
    )
    controller = "".join(f"<li>{escape(x.strip())}</li>" for x in _controller_lines(report)[1:])
    handover = "".join(
        f"<li>{escape(p['part'])} ({escape(p['part_type'])}) at {escape(p['location'])}, held "
        f"since {_short(p['since'])}: {escape(p['why'])}</li>"
        for p in report["held_at_end"]
    ) + "".join(
        f"<li>alarm {a['id']} {escape(a['machine'])} {escape(a['code'])} "
        f"({escape(a['priority'])}) since {_short(a['raised'])}: {escape(a['text'])}; "
        f"{escape(alarm_standing(a))}</li>"
        for a in report["open_alarms_at_end"]
    )
    alarms = "".join(
        f"<tr><td>{escape(a['code'])}</td><td>{escape(a['priority'])}</td><td>{a['count']}</td>"
        f"<td>{escape(', '.join(a['machines']))}</td></tr>"
        for a in report["alarms_by_cause"]
    )
    downs = "".join(
        f"<tr><td>{escape(d['machine'])}</td><td>{escape(d['reason'])}</td>"
        f"<td>{_hms(d['seconds'])}</td></tr>"
        for d in report["downtime_by_reason"]
    )
    alarms = alarms or '<tr><td colspan="4">none</td></tr>'
    downs = downs or '<tr><td colspan="3">none</td></tr>'
    title = f"Shift report{' of ' + cell if cell else ''}"
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{escape(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; max-width: 1040px; }}
table {{ border-collapse: collapse; margin: 0.5em 0 1em; }}
td, th {{ border-bottom: 1px solid #ddd; padding: 2px 10px; text-align: right; }}
td:first-child, th:first-child {{ text-align: left; }}
svg {{ max-width: 100%; height: auto; }}
@media print {{ body {{ margin: 0; }} }}
</style></head><body>
<h1>{escape(title)}</h1>
<p>{_when(report["start"])} to {_when(report["end"])}
({_hms(report["end"] - report["start"])}; time scale {report["time_scale"]:g})</p>
<h2>Machines (OEE after ISO 22400)</h2>
<table><tr><th>machine</th><th>availability</th><th>performance</th><th>quality</th>
<th>OEE</th><th>producing</th><th>down</th><th>good / steps</th><th>failed, run time</th>
<th>good / parts</th></tr>
{rows}</table>
<p>Parts good {report["parts_good"]}, held {report["parts_held"]},
scrapped {report["parts_scrapped"]}.</p>
<h2>The controller</h2>
<p>{escape(_controller_lines(report)[0])}</p><ul>{controller}</ul>
<h2>Handover</h2>
<p>{escape(_handover_lines(report)[0])}</p><ul>{handover}</ul>
<h2>Alarms by cause</h2>
<table><tr><th>cause</th><th>priority</th><th>count</th><th>machines</th></tr>{alarms}</table>
<h2>Downtime by reason</h2>
<table><tr><th>machine</th><th>reason</th><th>time</th></tr>{downs}</table>
<h2>Gantt chart</h2>
{svg}
<p><small>Availability: time in steps over the window (a failed step's time while its
machine was down, the cell stopped included, is down time, not time in steps). Performance:
the finished steps' ideal time (the machines' own models) over the time in steps, so a
failed step's time in steps is a performance loss. Quality: good parts over the
parts the machine worked on that were finished or scrapped in the window. OEE: their
product. {NOT_KNOWN}: not known yet (no part ended, no time in steps). See docs/cell.md,
"The shift report".</small></p>
</body></html>
"""


#: A time of day as ``--from`` and ``--to`` take it (which day: :func:`report_window`).
_TIME_OF_DAY = re.compile(r"^\s*(\d{1,2}):(\d{2})\s*$")
#: What ``--from`` and ``--to`` take, for a refusal.
WHEN_FORMS = "say a date/time like 2026-11-25T06:00, or a time of day HH:MM (00:00 to 23:59)"


def _read_when(text: str, option: str) -> datetime | tuple[int, int]:
    """``text`` as a local date and time, or a time of day ``(hour, minute)``."""
    found = _TIME_OF_DAY.match(text)
    if found is not None:
        hour, minute = int(found[1]), int(found[2])
        if hour < 24 and minute < 60:
            return hour, minute
    else:
        try:
            moment = datetime.fromisoformat(text.strip())
            # A time with its zone is read in local time, as every other time here.
            return moment.astimezone().replace(tzinfo=None) if moment.tzinfo else moment
        except ValueError:
            pass
    raise click.BadParameter(f"{text!r}: {WHEN_FORMS}", param_hint=option)


def _stamp(moment: datetime, text: str, option: str) -> float:
    try:
        return moment.timestamp()
    except (OverflowError, OSError, ValueError):
        raise click.BadParameter(f"{text!r}: out of range", param_hint=option) from None


def _time_of_day(hm: tuple[int, int], ref: float, *, after: bool, strict: bool) -> datetime:
    """The last ``HH:MM`` before ``ref`` (at it too unless ``strict``), or with ``after``
    the first one after it."""
    origin = datetime.fromtimestamp(ref)
    moment = origin.replace(hour=hm[0], minute=hm[1], second=0, microsecond=0)
    if after:
        return moment if moment > origin else moment + timedelta(days=1)
    late = moment >= origin if strict else moment > origin
    return moment - timedelta(days=1) if late else moment


def report_window(
    start: str | None, end: str | None, now: Callable[[], float]
) -> tuple[float | None, float | None]:
    """``--from`` and ``--to`` as s since the epoch (None: not given: the API's default).

    Both take a date and time (local unless it says its zone) or ``HH:MM``, read as a shift
    lead means it, looking back: ``--to HH:MM`` is the last such time at or before now (the
    first after ``--from`` when that is a date and time), ``--from HH:MM`` the last before
    ``--to`` (or now): ``--from 22:00 --to 06:00`` is last night's shift. A window that ends
    before it starts is refused naming both ends (click.UsageError, exit code 2)."""
    first = None if start is None else _read_when(start, "--from")
    last = None if end is None else _read_when(end, "--to")
    until: float | None = None
    if isinstance(last, datetime):
        until = _stamp(last, str(end), "--to")
    elif last is not None:
        if isinstance(first, datetime):
            ref, after = _stamp(first, str(start), "--from"), True
        else:
            ref, after = now(), False
        until = _stamp(_time_of_day(last, ref, after=after, strict=False), str(end), "--to")
    if first is None:
        return None, until
    ends = until if until is not None else now()
    if isinstance(first, datetime):
        since = _stamp(first, str(start), "--from")
    else:
        since = _stamp(_time_of_day(first, ends, after=False, strict=True), str(start), "--from")
    if since >= ends:
        shown = ("" if until is not None else "now, ") + _minute(ends)
        raise click.UsageError(
            f"the report's window ends before it starts (from {_minute(since)} to {shown}): "
            "give --from before --to"
        )
    return since, until


def _minute(t: float) -> str:
    """``t`` to the minute, its seconds too if it has any (a refusal's times)."""
    moment = datetime.fromtimestamp(t)
    return moment.strftime("%Y-%m-%d %H:%M" + (":%S" if moment.second else ""))


async def _now() -> float:
    # On the cell's clock: the command's own loop (virtual in a test rig, real otherwise).
    return current_clock().now()


@click.group()
def report() -> None:
    """Figures from the journal: `report shift` (OEE, parts, alarms, downtime)."""


@report.command("shift")
@click.option("--from", "start", metavar="TIME",
              help="Window start: a date/time, or HH:MM, the last before --to (default: 8 h "
              "before --to).")  # fmt: skip
@click.option("--to", "end", metavar="TIME",
              help="Window end: a date/time, or HH:MM, the last one (the first after a "
              "dated --from) (default: now).")  # fmt: skip
@click.option("--csv", "csv_file", type=click.Path(dir_okay=False, path_type=Path),
              help="Also save the figures as CSV to this file.")  # fmt: skip
@click.option("--html", "html_file", type=click.Path(dir_okay=False, path_type=Path),
              help="Also save a one-page HTML report with the Gantt chart.")  # fmt: skip
@json_option
@click.pass_context
def report_shift(
    ctx: click.Context,
    start: str | None,
    end: str | None,
    csv_file: Path | None,
    html_file: Path | None,
    as_json: bool,
) -> None:
    """Availability, performance, quality and OEE per machine (ISO 22400), parts good, held
    and scrapped, alarms by cause and downtime by reason, over a shift."""
    params: dict[str, Any] = {}
    since, until = report_window(start, end, lambda: run(_now))
    if since is not None:
        params["since"] = since
    if until is not None:
        params["until"] = until
    found = cell_call(ctx, "report.shift", params)
    cell = str(cell_call(ctx, "cell.layout", {}).get("name", ""))
    if csv_file is not None:
        _save(csv_file, shift_csv(found))
    if html_file is not None:
        steps = cell_call(ctx, "steps.list", {"since": max(0.0, found["start"] - 86400)})
        _save(html_file, shift_html(found, steps, cell))
    if as_json:
        print_json(found)
        return
    for line in shift_lines(found, cell):
        print_line(line)
    for path in (csv_file, html_file):
        if path is not None:
            console.print(f"saved {path}", markup=False, highlight=False)


def _save(path: Path, text: str) -> None:
    try:
        write_output(path, text)
    except OSError as e:
        raise UsageError(f"{path}: cannot write: {e.strerror}") from None


__all__ = ["report", "shift_csv", "shift_html", "shift_lines"]
