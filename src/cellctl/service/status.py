"""The cell's status: one typed model that every surface reads by field (the API, the console,
the dashboard, OPC UA), its difference between two moments, and its JSON Schema.

::

    status = access.status()                         # a CellStatus, built once per change
    status.machines["cnc1"].condition                # Condition.BUSY: never a word search
    update = difference(old, status)                 # what a subscriber is pushed
    assert apply_update(old, update).stable() == status.stable()

**The difference** (``notify_status_update``'s params, :class:`StatusUpdate`): ``time``, and
only what changed, each whole -- ``cell`` when a field of it other than ``time`` changed;
``machines``: the machines (by name) one of whose fields changed, or that are new;
``machines_gone``: names no longer there; ``orders``, ``parts``, ``alarms``: the whole list
when it changed; ``events``: only the events that are new. Figures that move with the clock
alone (:data:`VOLATILE`: the cell's ``time``, a machine's ``busy_s`` (it grows during a step)
and ``utilization``, a progress' ``rate_per_s``, ``time_left_s`` and ``fraction``) do not make
an update of their own: they travel with their object's next change, and ``cell.status`` has
them current.

The records (:class:`CellStatus` and its parts, :class:`StatusUpdate`) live in
:mod:`cellctl.service.status_model` and are re-exported here; this module builds a status
(:func:`build_status`), takes and applies the difference, and renders the schema and
docs/api.md's tables.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from pydantic import BaseModel

from cellctl.cell.commands import ManualStep
from cellctl.cell.journal import Alarm, Journal, Part, Step
from cellctl.cell.model import MachineView
from cellctl.kinds import Condition
from cellctl.kinds.families import estimated_done
from cellctl.service.operator import may_be_in
from cellctl.service.orderdue import is_late
from cellctl.service.status_model import (
    STATUS_EVENTS,
    VOLATILE,
    AlarmInfo,
    CellInfo,
    CellMode,
    CellStatus,
    ErrorInfo,
    EventInfo,
    MachineStatus,
    OrderInfo,
    PartInfo,
    ProgressInfo,
    StatusUpdate,
    StepInfo,
    StepKind,
)

#: Orders a status carries.
STATUS_ORDERS = 30
#: Order states shown whatever their age (the others: the latest STATUS_ORDERS).
OPEN_ORDER_STATES = ("posted", "accepted", "in-progress", "held")
#: Part statuses the status lists (the parts in the cell).
SHOWN_PARTS = ["waiting", "active", "held"]


# -- the difference ---------------------------------------------------------------------------


def difference(old: CellStatus | None, new: CellStatus) -> StatusUpdate:
    """What a subscriber holding ``old`` is sent to hold ``new`` (``old`` None: everything)."""
    changes: dict[str, Any] = {}
    if old is None or old.cell.model_copy(update={"time": new.cell.time}) != new.cell:
        changes["cell"] = new.cell
    machines = {
        name: m
        for name, m in new.machines.items()
        if old is None or name not in old.machines or old.machines[name].stable() != m.stable()
    }
    if machines:
        changes["machines"] = machines
    gone = [name for name in (old.machines if old else {}) if name not in new.machines]
    if gone:
        changes["machines_gone"] = gone
    for key in ("orders", "parts", "alarms"):
        if old is None or getattr(old, key) != getattr(new, key):
            changes[key] = getattr(new, key)
    fresh = new_events(old.events if old else [], new.events)
    if fresh:
        changes["events"] = fresh
    return StatusUpdate(time=new.cell.time, **changes)


def new_events(old: list[EventInfo], new: list[EventInfo]) -> list[EventInfo]:
    """The events of ``new`` that ``old`` does not have: both are windows on one log, so
    ``old`` ends with what ``new`` starts with (nothing in common: more happened than a
    status carries, and every event of ``new`` is new)."""
    for k in range(min(len(old), len(new)), 0, -1):
        if old[-k:] == new[:k]:
            return new[k:]
    return list(new)


def apply_update(old: CellStatus, update: StatusUpdate) -> CellStatus:
    """``old`` with ``update`` applied: what a subscriber holds after it."""
    machines = dict(old.machines)
    for name in update.machines_gone or []:
        machines.pop(name, None)
    machines.update(update.machines or {})
    events = [*old.events, *(update.events or [])][-STATUS_EVENTS:]
    return CellStatus(
        cell=update.cell or old.cell,
        machines=machines,
        orders=old.orders if update.orders is None else update.orders,
        parts=old.parts if update.parts is None else update.parts,
        alarms=old.alarms if update.alarms is None else update.alarms,
        events=events,
    )


def apply_update_json(snapshot: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    """:func:`apply_update` on the JSON a client holds and is pushed (the console's way)."""
    out = dict(snapshot)
    machines = dict(out.get("machines", {}))
    for name in update.get("machines_gone", []):
        machines.pop(name, None)
    machines.update(update.get("machines", {}))
    out["machines"] = machines
    for key in ("cell", "orders", "parts", "alarms"):
        if key in update:
            out[key] = update[key]
    out["events"] = [*out.get("events", []), *update.get("events", [])][-STATUS_EVENTS:]
    return out


# -- building it ------------------------------------------------------------------------------


def build_status(
    *,
    cell: CellInfo,
    views: Mapping[str, MachineView],
    families: Mapping[str, str],
    out_of_service: Mapping[str, str],
    manual: Iterable[str],
    journal: Journal | None,
    orders: list[dict[str, Any]],
    events: Iterable[tuple[float, str]],
    estimates: Mapping[tuple[str, str], float] | None = None,
    manual_steps: Mapping[str, ManualStep] | None = None,
) -> CellStatus:
    """The status from what the controller (or a standalone cell) knows: each machine's view,
    the journal's steps in flight, parts and alarms, the orders (``orders.list``'s entries,
    :func:`cellctl.service.orderdue.list_orders`, each with its ``due`` time: one without
    has none), the events. ``estimates``:
    a program's own machining seconds by (machine, route step name); ``manual_steps``: the
    manual functions running (their program and start), by machine."""
    now = cell.time
    parts = journal.parts(SHOWN_PARTS) if journal is not None else []
    open_steps = {s.machine: s for s in journal.open_steps()} if journal is not None else {}
    manual_use = set(manual)
    machines = {
        name: _machine(
            view,
            families.get(name, view.kind),
            open_steps.get(name),
            parts,
            out_of_service.get(name, ""),
            name in manual_use,
            now,
            cell.started_at,
            estimates or {},
            (manual_steps or {}).get(name),
        )
        for name, view in views.items()
    }
    alarms: list[Alarm] = journal.active_alarms() if journal is not None else []
    shown = [o for o in orders if o["state"] in OPEN_ORDER_STATES]
    shown += [o for o in orders if o["state"] not in OPEN_ORDER_STATES][:STATUS_ORDERS]
    return CellStatus(
        cell=cell,
        machines=machines,
        orders=[_order(o, now) for o in shown[: STATUS_ORDERS * 2]],
        parts=[_part(p, may_be_in(journal, p) if journal is not None else []) for p in parts],
        alarms=[_alarm(a) for a in alarms],
        events=[EventInfo(time=t, text=x) for t, x in events][-STATUS_EVENTS:],
    )


def _machine(
    view: MachineView,
    family: str,
    journal_step: Step | None,
    parts: list[Part],
    out_reason: str,
    manual: bool,
    now: float,
    started_at: float,
    estimates: Mapping[tuple[str, str], float],
    manual_step: ManualStep | None = None,
) -> MachineStatus:
    step: StepInfo | None = None
    if view.step:
        # The journal has the step's facts (what, which part); a step the journal does
        # not know is the operator's manual function.
        if journal_step is not None:
            step = StepInfo(
                what=StepKind(journal_step.kind),
                program=journal_step.program,
                part_id=journal_step.part_id,
                started=journal_step.started,
            )
        elif manual_step is not None:
            step = StepInfo(
                what=StepKind.MANUAL, program=manual_step.program, started=manual_step.started
            )
        else:
            step = StepInfo(what=StepKind.MANUAL)
    part = step.part_id if step is not None and step.part_id else None
    if part is None:
        part = next((p.id for p in parts if p.location == view.name), None)
    estimate = None
    if step is not None and step.program is not None:
        estimate = estimates.get((view.name, step.program))
    progress = _progress(view.progress, now, estimate, step)
    error = ErrorInfo(code=view.error.code, text=view.error.text) if view.error else None
    elapsed = max(now - started_at, 1e-6)
    # The step in flight counts as it runs: a mill an hour into its first cut is busy, not
    # "0 %" until the cut ends.
    busy = view.busy_s
    # (A manual function's time is the operator's, not the cell's: it does not count.)
    if step is not None and step.started is not None and step.what is not StepKind.MANUAL:
        busy += max(0.0, now - max(step.started, started_at))
    return MachineStatus(
        name=view.name,
        kind=view.kind,
        family=family,
        condition=view.condition,
        state=view.state,
        step=step,
        part=part,
        progress=progress,
        error=error,
        failures=view.failures,
        busy_s=round(busy, 3),
        utilization=round(min(1.0, busy / elapsed), 4),
        in_service=view.in_service,
        out_reason=out_reason,
        manual=manual,
    )


def _progress(
    raw: Mapping[str, Any] | None, now: float, estimate: float | None, step: StepInfo | None
) -> ProgressInfo | None:
    if not raw:
        return None
    done, total = int(raw.get("done", 0)), int(raw.get("total", 0))
    since = raw.get("since")
    if since is None and step is not None:
        since = step.started
    rate = None
    if since is not None and now > since and done > 0:
        rate = done / (now - float(since))
    left = None
    fraction = min(1.0, done / total) if total > 0 else 0.0
    run_total = float(raw.get("estimate_s") or 0.0)
    run_done = estimated_done(raw, now)
    if run_done is not None:
        # The run's estimate, corrected by the machine's reports: the bar moves through a
        # cut that sends no byte, and the time left counts the cut still to come.
        fraction = run_done / run_total
        left = run_total - run_done
    elif rate and done < total:
        left = (total - done) / rate
    elif estimate is not None and step is not None and step.started is not None:
        left = max(0.0, estimate - (now - step.started))
    return ProgressInfo(
        phase=str(raw.get("phase", "")),
        done=done,
        total=total,
        unit=str(raw.get("unit", "")),
        fraction=round(fraction, 4),
        estimate_s=round(run_total, 3) if run_done is not None else None,
        estimate_done_s=None if run_done is None else float(raw.get("estimate_done_s") or 0),
        estimate_cap_s=None if run_done is None else float(raw.get("estimate_cap_s") or 0),
        estimate_at=None if run_done is None else float(raw.get("at") or 0),
        running=bool(raw.get("running")) and run_done is not None,
        program=raw.get("program"),
        block=raw.get("block"),
        blocks=raw.get("blocks"),
        since=None if since is None else float(since),
        rate_per_s=None if rate is None else round(rate, 3),
        time_left_s=None if left is None else round(left, 1),
    )


def _order(entry: Mapping[str, Any], now: float) -> OrderInfo:
    """An order as the status carries it: ``late`` at the status' own time (``now``, its
    ``cell.time``), by orders.list's rule, so that a client comparing the two agrees."""
    late = is_late(entry["state"], entry["updated"], entry.get("due"), now)
    return OrderInfo(**{**entry, "late": late})


def _part(p: Part, places: list[str]) -> PartInfo:
    return PartInfo(
        id=p.id,
        order_id=p.order_id,
        part_type=p.part_type,
        seq_in_order=p.seq_in_order,
        route_index=p.route_index,
        location=p.location,
        status=p.status,
        updated=p.updated,
        note=p.note,
        may_be_in=places,
    )


def _alarm(a: Alarm) -> AlarmInfo:
    return AlarmInfo(
        id=a.id,
        raised=a.raised,
        machine=a.machine,
        code=a.code,
        text=a.text,
        state=a.state,
        cleared=a.cleared,
        cleared_by=a.cleared_by,
        priority=a.priority,
        acked=a.acked,
        acked_by=a.acked_by,
        returned=a.returned,
        shelved_until=a.shelved_until,
    )


# -- the schema and docs/api.md's tables ------------------------------------------------------


def status_schema() -> dict[str, Any]:
    """The JSON Schema of the status and of an update (``GET /api/schema``)."""
    return {
        "status": CellStatus.model_json_schema(),
        "update": StatusUpdate.model_json_schema(),
    }


#: The objects docs/api.md's tables describe, in order.
_TABLES: list[tuple[str, type[BaseModel]]] = [
    ("status", CellStatus),
    ("cell", CellInfo),
    ("machines.NAME", MachineStatus),
    ("machines.NAME.step", StepInfo),
    ("machines.NAME.progress", ProgressInfo),
    ("machines.NAME.error", ErrorInfo),
    ("orders[]", OrderInfo),
    ("parts[]", PartInfo),
    ("alarms[]", AlarmInfo),
    ("events[]", EventInfo),
    ("update (notify_status_update)", StatusUpdate),
]


def status_tables() -> str:
    """The status' fields as Markdown tables, rendered from the schema (docs/api.md holds
    exactly this between its ``status tables`` markers)."""
    schema = status_schema()
    defs = {**schema["status"].get("$defs", {}), **schema["update"].get("$defs", {})}
    out: list[str] = []
    for title, model in _TABLES:
        found = model.model_json_schema()
        out += [f"**{title}**", "", "| field | type | meaning |", "|---|---|---|"]
        required = set(found.get("required", []))
        for key, prop in found["properties"].items():
            kind = _type_of(prop, defs) + ("" if key in required else ", optional")
            if model is StatusUpdate and key != "time":
                kind = _type_of(prop, defs).removesuffix(" or null") + ", only when changed"
            out.append(f"| `{key}` | {kind} | {prop.get('description', '')} |")
        out.append("")
    conditions = ", ".join(f"`{c.value}`" for c in Condition)
    modes = ", ".join(f"`{m.value}`" for m in CellMode)
    out.append(f"A machine's `condition` is one of {conditions}; the cell's `mode` one of {modes}.")
    return "\n".join(out) + "\n"


def _type_of(prop: dict[str, Any], defs: dict[str, Any]) -> str:
    if "$ref" in prop:
        name = str(prop["$ref"]).rsplit("/", 1)[-1]
        found = defs.get(name, {})
        if "enum" in found:
            return " \\| ".join(f"`{v}`" for v in found["enum"])
        return name
    if "anyOf" in prop:
        kinds = [_type_of(p, defs) for p in prop["anyOf"]]
        return " or ".join(k for k in kinds if k != "null") + (
            " or null" if "null" in kinds else ""
        )
    if "enum" in prop:
        return " \\| ".join(f"`{v}`" for v in prop["enum"])
    if "const" in prop:
        return f"`{prop['const']}`"
    kind = prop.get("type", "any")
    if kind == "array":
        return f"list of {_type_of(prop.get('items', {}), defs)}"
    if kind == "object" and "additionalProperties" in prop:
        return f"map of {_type_of(prop['additionalProperties'], defs)}"
    return str(kind)


__all__ = [
    "OPEN_ORDER_STATES",
    "SHOWN_PARTS",
    "STATUS_EVENTS",
    "STATUS_ORDERS",
    "VOLATILE",
    "AlarmInfo",
    "CellInfo",
    "CellMode",
    "CellStatus",
    "ErrorInfo",
    "EventInfo",
    "MachineStatus",
    "OrderInfo",
    "PartInfo",
    "ProgressInfo",
    "StatusUpdate",
    "StepInfo",
    "StepKind",
    "apply_update",
    "apply_update_json",
    "build_status",
    "difference",
    "new_events",
    "status_schema",
    "status_tables",
]
