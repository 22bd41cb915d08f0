"""``cellctl report shift``: the figures a shift lead reads, from the journal.

::

    cellctl report shift                                # the last 8 h, a table at 80 columns
    cellctl report shift --from 2026-11-25T06:00 --to 2026-11-25T14:00 --csv shift.csv
    cellctl report shift --html shift.html --json

The figures (availability, performance, quality and OEE per machine after ISO 22400, parts,
alarms by cause, downtime by reason) and their definitions are :mod:`cellctl.cell.shift`'s;
they come through the control API's ``report.shift``, so the dashboard's Shift panel shows
the same numbers.
"""

from __future__ import annotations

import csv
import io
from datetime import datetime
from html import escape
from pathlib import Path
from typing import Any

import click

from cellctl.cell.journal import Step
from cellctl.cell.report import gantt_svg
from cellctl.errors import UsageError
from cellctl.files import write_output
from cellctl.ui.calls import cell_call
from cellctl.ui.common import console, json_option, print_json, print_line

#: The table's width: it fits an 80-column terminal.
WIDTH = 80


def _when(t: float) -> str:
    return datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S")


def _hms(seconds: float) -> str:
    if seconds < 60:  # an emulated cell's short runs: tenths still say something
        return f"{seconds:.1f} s"
    s = round(seconds)
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


#: A ratio not known yet (its denominator 0: no step ended, no time in steps).
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
        f"{'producing':>10} {'down':>9} {'steps':>6}",
    ]
    for m in report["machines"]:
        out.append(
            f"{_clip(m['machine'], 10):<10} {_pct(m['availability']):>7} "
            f"{_pct(m['performance']):>7} {_pct(m['quality']):>7} {_pct(m['oee']):>7} "
            f"{_hms(m['production_s']):>10} {_hms(m['down_s']):>9} "
            f"{m['steps_good']:>3}/{m['steps_ended']:<2}"
        )
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
    return out


def shift_csv(report: dict[str, Any]) -> str:
    """The report as CSV: one row per figure, ``section,name,field,value`` (a ratio not
    known yet has an empty value)."""
    buffer = io.StringIO()
    out = csv.writer(buffer, lineterminator="\n")
    out.writerow(["section", "name", "field", "value"])
    out.writerow(["window", "", "start", _when(report["start"])])
    out.writerow(["window", "", "end", _when(report["end"])])
    out.writerow(["window", "", "time_scale", report["time_scale"]])
    for m in report["machines"]:
        for key, value in m.items():
            if key != "machine":
                out.writerow(["machine", m["machine"], key, value])
    for key in ("parts_good", "parts_held", "parts_scrapped"):
        out.writerow(["parts", "", key.removeprefix("parts_"), report[key]])
    for a in report["alarms_by_cause"]:
        out.writerow(["alarms", a["code"], "count", a["count"]])
        out.writerow(["alarms", a["code"], "priority", a["priority"]])
    for d in report["downtime_by_reason"]:
        out.writerow(["downtime", d["machine"], d["reason"], d["seconds"]])
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
        f"<td>{_hms(m['down_s'])}</td><td>{m['steps_good']} / {m['steps_ended']}</td></tr>"
        for m in report["machines"]
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
<th>OEE</th><th>producing</th><th>down</th><th>good / steps</th></tr>{rows}</table>
<p>Parts good {report["parts_good"]}, held {report["parts_held"]},
scrapped {report["parts_scrapped"]}.</p>
<h2>Alarms by cause</h2>
<table><tr><th>cause</th><th>priority</th><th>count</th><th>machines</th></tr>{alarms}</table>
<h2>Downtime by reason</h2>
<table><tr><th>machine</th><th>reason</th><th>time</th></tr>{downs}</table>
<h2>Gantt chart</h2>
{svg}
<p><small>Availability: time in steps over the window. Performance: the finished steps'
ideal time (the machines' own models) over the time in steps. Quality: good steps over
steps ended. OEE: their product. {NOT_KNOWN}: not known yet (no step ended, no time in
steps). See docs/cell.md, "The shift report".</small></p>
</body></html>
"""


def _time(text: str | None, option: str) -> float | None:
    if text is None:
        return None
    try:
        return datetime.fromisoformat(text.strip()).timestamp()
    except (ValueError, OverflowError, OSError):
        raise click.BadParameter(
            f"{text!r}: say a date/time like 2026-11-25T06:00", param_hint=option
        ) from None


@click.group()
def report() -> None:
    """Figures from the journal: `report shift` (OEE, parts, alarms, downtime)."""


@report.command("shift")
@click.option("--from", "start", metavar="TIME", help="Window start (default: 8 h before --to).")
@click.option("--to", "end", metavar="TIME", help="Window end, a date/time (default: now).")
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
    since, until = _time(start, "--from"), _time(end, "--to")
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
