"""The operator's actions on a cell's orders, alarms and parts: one implementation for every
surface (the CLI without a controller, the control API, the console).

Each action writes the journal or the mailbox, posts the report the system level expects, and
returns a JSON-ready dict (what the API answers and the CLI prints)::

    with open_journal(cell) as journal, open_mailbox(cell) as mailbox:
        result = clear_alarm(journal, mailbox, 3)       # {"alarm": {...}, "message": "..."}
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Mapping
from typing import Any

from cellctl.cell.blocked import blocked_reason
from cellctl.cell.config import CONVEYOR, CellConfig, mill_names, transfer_ends
from cellctl.cell.journal import Alarm, Journal, Part
from cellctl.cell.orderflow import OUT
from cellctl.cell.workview import places_of
from cellctl.errors import UsageError
from cellctl.mailbox import Mailbox, Order, Report, ReportKind

#: Order states in which an order may still be cancelled (no part has started).
CANCELLABLE = ("posted", "accepted")


def as_dict(item: Order | Part | Alarm | Report) -> dict[str, Any]:
    """A journal or mailbox record as JSON-ready values."""
    return dataclasses.asdict(item)


def may_be_in(journal: Journal, part: Part) -> list[str]:
    """The machines a held part may physically be in (``taken_out`` scraps it); [] for a
    part not held."""
    return sorted(places_of(journal, part)) if part.status == "held" else []


def part_entry(journal: Journal, part: Part) -> dict[str, Any]:
    """A part as ``parts.list`` gives it: its record and ``may_be_in``."""
    return {**as_dict(part), "may_be_in": may_be_in(journal, part)}


def scrap_question(part_id: str, places: list[str]) -> str:
    """What a surface asks before it scraps a part that ``may_be_in`` ``places``."""
    if not places:
        return f"Scrap part {part_id}? This cannot be undone."
    where = " or ".join(places)
    return (
        f"Scrap part {part_id}? It may be in {where}: take it out first (the cell loads "
        f"{where} again at once). Is it out? This cannot be undone."
    )


def resolve_part_id(journal: Journal, text: str) -> str:
    """A part id from the id itself, a unique prefix of it, or a unique prefix of its order's
    id with the part's number (``9227-2`` for ``9227175d00c...-2``), as git takes commit ids."""
    parts = journal.parts()
    if any(p.id == text for p in parts):
        return text
    matches = [p.id for p in parts if p.id.startswith(text)] if text else []
    order, sep, number = text.rpartition("-")
    if not matches and sep and order and number.isdecimal():
        matches = [
            p.id for p in parts if p.order_id.startswith(order) and p.seq_in_order == int(number)
        ]
    if len(matches) == 1:
        return matches[0]
    if not matches:
        raise UsageError(f"no part {text!r}")
    raise UsageError(f"part id {text!r} is ambiguous: {', '.join(sorted(matches)[:5])} ...")


def short_part_id(part_id: str, order_id: str, order_ids: list[str], least: int = 4) -> str:
    """The shortest name :func:`resolve_part_id` takes for a part: its order id cut to the
    shortest unique prefix (at least ``least`` characters), then ``-N``."""
    suffix = part_id[len(order_id) :] if part_id.startswith(order_id) else ""
    if not suffix:
        return part_id
    for n in range(least, len(order_id)):
        prefix = order_id[:n]
        if not any(o != order_id and o.startswith(prefix) for o in order_ids):
            return prefix + suffix
    return part_id


def check_part_type(part_types: list[str] | None, part_type: str) -> None:
    """Refuse a part type that cell.toml does not define (None: no cell.toml, not checked)."""
    if part_types is not None and part_type not in part_types:
        known = ", ".join(sorted(part_types)) or "none"
        raise UsageError(f"unknown part type {part_type!r} (known in cell.toml: {known})")


def list_orders(
    mailbox: Mailbox,
    journal: Journal | None,
    states: list[str] | None = None,
    config: CellConfig | None = None,
) -> list[dict[str, Any]]:
    """Orders with their parts counted by status, highest priority first, then oldest.

    With the cell's ``config``, an open order whose parts wait for a machine out of service
    says so: ``blocked`` (also put before its ``note``), e.g. "blocked: its parts need cnc2,
    out of service (...)" (:mod:`cellctl.cell.blocked`), or "blocked: every transfer waits
    until alarm 3 is cleared (door of CNC 1 ...)" for a stuck door; "" otherwise."""
    progress: dict[str, Counter[str]] = {}
    by_order: dict[str, list[Part]] = {}
    out: dict[str, str] = {}
    if journal is not None:
        for part in journal.parts():
            progress.setdefault(part.order_id, Counter())[part.status] += 1
            by_order.setdefault(part.order_id, []).append(part)
        out = journal.machines_out_of_service() if config is not None else {}
    # A door or vise the PLC failed to move holds every transfer until its alarm is cleared
    # (cell.recovery): an order that waits on it says so, or the cell just looks idle.
    door = journal.open_alarm("plc", "interlock") if journal is not None else None
    found = []
    for o in mailbox.orders(states or None):
        entry = {**as_dict(o), "parts": dict(sorted(progress.get(o.id, Counter()).items()))}
        blocked = ""
        if config is not None and o.state in BLOCKABLE:
            parts = by_order.get(o.id, [])
            blocked = blocked_reason(config, o.part_type, parts, out)
            if not blocked and door is not None and not any(p.status == "active" for p in parts):
                blocked = (
                    f"blocked: every transfer waits until alarm {door.id} is cleared ({door.text})"
                )
        entry["blocked"] = blocked
        if blocked:
            entry["note"] = f"{blocked}; {o.note}" if o.note else blocked
        found.append(entry)
    return found


#: Order states in which an order may wait for a machine.
BLOCKABLE = ("posted", "accepted", "in-progress", "held")


def cancel_order(mailbox: Mailbox, journal: Journal | None, order_id: str) -> dict[str, Any]:
    """Cancel an order that has not started: posted, or accepted with no part moved yet."""
    order = mailbox.get_order(order_id)
    if order.state not in CANCELLABLE:
        raise UsageError(
            f"order {order_id} is {order.state}: only an order that has not started "
            "can be cancelled"
        )
    parts = journal.cancel_parts(order_id) if journal is not None else []
    order = mailbox.set_order_state(order_id, "cancelled", "cancelled by the operator")
    mailbox.post_report(
        ReportKind.ORDER_CANCELLED, f"order {order_id} cancelled", order_id=order_id
    )
    return {
        "order": as_dict(order),
        "message": f"order {order_id} cancelled ({len(parts)} part(s) not started)",
    }


def clear_alarm(
    journal: Journal, mailbox: Mailbox, alarm_id: int, by: str = "operator"
) -> dict[str, Any]:
    """Clear an alarm once its cause is dealt with; clearing it again changes nothing."""
    before = journal.get_alarm(alarm_id)
    if before.state == "cleared":
        return {"alarm": as_dict(before), "message": f"alarm {alarm_id} was already cleared"}
    a = journal.clear_alarm(alarm_id, by=by)
    mailbox.post_report(
        ReportKind.ALARM_CLEARED,
        f"alarm {a.id} cleared by {by}: {a.machine} {a.code} {a.text}",
        data={"alarm": a.id, "machine": a.machine, "code": a.code, "by": by},
    )
    return {
        "alarm": as_dict(a),
        "message": f"alarm {a.id} cleared ({a.machine} {a.code}: {a.text})",
    }


def ack_alarm(journal: Journal, alarm_id: int, by: str = "operator") -> dict[str, Any]:
    """Acknowledge an alarm (it stays open until cleared); again changes nothing."""
    before = journal.get_alarm(alarm_id)
    if before.state == "cleared":
        return {"alarm": as_dict(before), "message": f"alarm {alarm_id} is already cleared"}
    if before.acked is not None:
        return {"alarm": as_dict(before), "message": f"alarm {alarm_id} was already acknowledged"}
    a = journal.ack_alarm(alarm_id, by=by)
    return {
        "alarm": as_dict(a),
        "message": f"alarm {a.id} acknowledged ({a.machine} {a.code}: {a.text})",
    }


def shelve_alarm(
    journal: Journal, alarm_id: int, seconds: float, by: str = "operator"
) -> dict[str, Any]:
    """Shelve an open alarm for ``seconds`` (at most 8 h): it is not shown as unacknowledged
    until then."""
    a = journal.shelve_alarm(alarm_id, seconds, by=by)
    what = f"{a.machine} {a.code}: {a.text}"
    return {
        "alarm": as_dict(a),
        "message": f"alarm {a.id} shelved for {_duration(seconds)} ({what})",
    }


def unshelve_alarm(journal: Journal, alarm_id: int, by: str = "operator") -> dict[str, Any]:
    """Unshelve an alarm shelved now: shown as it is again at once (refused for one that is
    cleared or not shelved, in words)."""
    a = journal.unshelve_alarm(alarm_id, by=by)
    return {
        "alarm": as_dict(a),
        "message": f"alarm {a.id} unshelved ({a.machine} {a.code}: {a.text})",
    }


def _duration(seconds: float) -> str:
    whole = round(seconds)
    h, rest = divmod(whole, 3600)
    m, s = divmod(rest, 60)
    return " ".join(f"{n}{u}" for n, u in ((h, "h"), (m, "m"), (s, "s")) if n) or f"{seconds:g}s"


@dataclasses.dataclass(frozen=True)
class CellPlaces:
    """Where a part can be in a cell: its ``mills``, and each part type's route (``routes``:
    the mills of its cuts, in order): what a released part's place is checked against."""

    mills: tuple[str, ...]
    routes: Mapping[str, tuple[str, ...]]

    @classmethod
    def of_config(cls, config: CellConfig) -> CellPlaces:
        """A checked cell's (a running controller's)."""
        routes = {name: tuple(s.mill for s in t.route) for name, t in config.parts.items()}
        return cls(tuple(m.name for m in config.mills), routes)

    @classmethod
    def of_file(cls, cell: Mapping[str, Any]) -> CellPlaces | None:
        """A parsed cell.toml's as it stands (None: it has no machines to say)."""
        machines = cell.get("machines")
        if not isinstance(machines, dict) or not machines:
            return None
        kinds = {n: m.get("kind") for n, m in machines.items() if isinstance(m, dict)}
        table = cell.get("cell")
        mills = mill_names(table.get("mills") if isinstance(table, dict) else None, kinds)
        routes: dict[str, tuple[str, ...]] = {}
        parts = cell.get("parts")
        for name, part in (parts if isinstance(parts, dict) else {}).items():
            route = part.get("route") if isinstance(part, dict) else None
            if isinstance(route, list):
                routes[name] = tuple(str(s.get("mill")) for s in route if isinstance(s, dict))
        return cls(tuple(mills), routes)

    def check_release(
        self, part: Part, location: str, cuts_done: int, occupant: str | None = None
    ) -> None:
        """Refuse releasing ``part`` at ``location`` where the cell could never take it up
        again (it would wait there for ever, and its order with it), or in a mill whose vise
        holds part ``occupant``; ``cuts_done``: how many of its route's cuts count as done
        once it is released there."""
        route = self.routes.get(part.part_type)
        if route is None:  # a part type no longer in cell.toml: any place of the cell
            places = [CONVEYOR, *self.mills, OUT]
        else:
            cuts_done = min(cuts_done, len(route))
            places = [CONVEYOR] if cuts_done == 0 else [route[cuts_done - 1]]
            places += [route[cuts_done]] if cuts_done < len(route) else [OUT]
        if location in places:
            if occupant is not None and location in self.mills:
                raise UsageError(
                    f"part {part.id} cannot be released at {location}: the journal has part "
                    f"{occupant} in its vise; scrap or release that one first"
                )
            return
        said = " or ".join(dict.fromkeys(places))
        raise UsageError(
            f"part {part.id} cannot be released at {location!r}: with "
            f"{cuts_done} of its {len(route)} cuts done the cell takes it up again only at "
            f"{said}; put it there and say so, or scrap it"
            if route is not None
            else f"part {part.id} cannot be released at {location!r}: the cell takes a part "
            f"up again only at {said}"
        )


def release_part(
    journal: Journal,
    mailbox: Mailbox,
    part_id: str,
    *,
    redo: bool = False,
    location: str | None = None,
    places: CellPlaces | None = None,
) -> dict[str, Any]:
    """Release a held part after inspection: the cell carries on with it. The machines it may
    have been in and is not (``location`` said elsewhere) are emptied by the operator's word:
    a vise closed there is opened before they are loaded (docs/cell.md). ``places``: the
    cell's, which ``location`` is checked against (None: not known, any one word)."""
    part_id = resolve_part_id(journal, part_id)
    part = journal.get_part(part_id)
    if location is not None and places is not None and part.status == "held":
        occupant = next(
            (
                q.id
                for q in journal.parts(statuses=["waiting", "active", "held"])
                if q.location == location and q.id != part.id
            ),
            None,
        )
        places.check_release(part, location, _cuts_done(journal, part, location, redo), occupant)
    at = location or part.location
    was_in = places_of(journal, part) if part.status == "held" else set()
    emptied = sorted(was_in - {at})
    steps = journal.steps(part.id) if part.status == "held" else []
    held = steps[-1] if steps else None
    p = journal.release_part(part_id, redo_step=redo, location=location, emptied=emptied)
    what = "its interrupted step will run again" if redo else "its interrupted step counts as done"
    carried_again = (
        not redo
        and held is not None
        and held.kind == "transfer"
        and held.state != "finished"
        and at != transfer_ends(held.program)[1]
    )
    if carried_again:
        # Accepted, but the part is not where the transfer was taking it: the cell carries
        # it on from where it is, which is that transfer again.
        what = f"the cell takes it up at {at}, so its interrupted transfer will run again"
    mailbox.post_report(
        ReportKind.PART_RELEASED,
        f"part {p.id} released by operator at {p.location}: {what}",
        order_id=p.order_id,
        part_id=p.id,
        # Released on the outfeed, its route machined: the cell counts it done (the factory
        # counts it made by ``part_done``, as the step that brings a part out says it).
        data={"redo": redo, "location": p.location, "part_done": p.location == OUT},
    )
    return {"part": as_dict(p), "message": f"part {p.id} released at {p.location}: {what}"}


def _cuts_done(journal: Journal, part: Part, location: str, redo: bool) -> int:
    """The cuts ``part`` (held) will have done once released at ``location``: the cut it was
    held in counts too when it is accepted (not ``redo``) and the part is still in that mill
    (what the controller then goes on from)."""
    steps = journal.steps(part.id)
    held = steps[-1] if steps else None
    accepted_cut = (
        held is not None
        and held.kind == "machine"
        and held.state != "finished"
        and held.machine == location
        and not redo
    )
    return part.route_index + (1 if accepted_cut else 0)


def scrap_part(
    journal: Journal,
    mailbox: Mailbox,
    part_id: str,
    reason: str = "scrapped by operator",
    *,
    taken_out: bool = False,
) -> dict[str, Any]:
    """Scrap a held or waiting part: the cell will not work on it again.

    A part that may be in a machine (its place, or where an interrupted transfer took it) is
    scrapped only once the operator says it is out (``taken_out``): the journal forgets it,
    and the cell loads that machine again once its vise is open (the robot's
    ``open_vise_<mill>`` program opens it: docs/cell.md)."""
    part_id = resolve_part_id(journal, part_id)
    part = journal.get_part(part_id)
    # Only a part that can be scrapped is asked about (the journal refuses the others).
    places = sorted(places_of(journal, part)) if part.status in ("waiting", "held") else []
    in_machines = " or ".join(places)
    if places and not taken_out:
        raise UsageError(
            f"part {part_id} may be in {in_machines}: take it out, then scrap it saying so "
            f"(taken out; `cellctl part scrap {part_id} --taken-out`): the cell loads "
            f"{in_machines} again as soon as it is scrapped"
        )
    # The places it was taken out of are kept: their vises are opened before they are loaded.
    p = journal.scrap_part(part_id, reason, taken_out_of=places)
    mailbox.post_report(
        ReportKind.PART_SCRAPPED,
        f"part {p.id} scrapped: {reason}",
        order_id=p.order_id,
        part_id=p.id,
        data={"reason": reason, "location": p.location, "taken_out_of": places},
    )
    message = f"part {p.id} scrapped"
    if places:
        again = (
            "which takes parts again once its vise is open"
            if len(places) == 1
            else "which take parts again once their vises are open"
        )
        message += f"; taken out of {in_machines}, {again}"
    return {"part": as_dict(p), "message": message}
