"""What the factory keeps of its orders, its cells and its events, as the store hands them
out (:mod:`cellctl.factory.store`): the order states, one order, one cell as last heard, one
event. ``from cellctl.factory.store import ...`` finds every name here too."""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from cellctl.mailbox.wire import ReportKind

#: Order states: at no cell yet, sent, and as the cell's reports say.
QUEUED, SENT, ACCEPTED, IN_PROGRESS, HELD = "queued", "sent", "accepted", "in-progress", "held"
DONE, FAILED, CANCELLED = "done", "failed", "cancelled"
OPEN_STATES = (QUEUED, SENT, ACCEPTED, IN_PROGRESS, HELD)
AT_CELL_STATES = (ACCEPTED, IN_PROGRESS, HELD)
FINAL_STATES = (DONE, FAILED, CANCELLED)
#: How an order at a cell is shown while its cancel is on its way (not a state of its own).
CANCELLING = "cancelling"
#: The columns a store from before cancels (or before held parts by id, or before due
#: times) lacks, with their SQL types.
CANCEL_COLUMNS = {
    "held_parts": "TEXT NOT NULL DEFAULT '[]'",
    "cancel_asked": "REAL",
    "cancel_by": "TEXT",
    "cancel_reason": "TEXT",
    "cancel_sent": "REAL",
    "cancel_sends": "INTEGER NOT NULL DEFAULT 0",
    "due": "REAL",
}
#: Reports that answer an order: taken again when a re-sent order is answered again.
ANSWER_KINDS = (ReportKind.ORDER_ACCEPTED, ReportKind.ORDER_REJECTED)
#: Reports that end an order, and the state each ends it in.
ENDS = {
    ReportKind.ORDER_DONE: DONE,
    ReportKind.ORDER_FAILED: FAILED,
    ReportKind.ORDER_CANCELLED: CANCELLED,
}


@dataclass(frozen=True)
class FactoryOrder:
    """One order as the factory follows it."""

    id: str
    part_type: str
    qty: int
    priority: int
    state: str
    cell: str | None
    note: str
    submitted: float
    updated: float
    sent: float | None
    last_send: float | None
    sends: int
    expires: float | None
    accepted: float | None  # the cell's time of its order-accepted report
    accepted_seen: float | None  # when the factory got it
    finished: float | None
    refused: tuple[str, ...]
    done: int
    held: int
    scrapped: int
    cancel_asked: float | None = None  # when a cancel was asked (None: none on its way)
    cancel_by: str | None = None
    cancel_reason: str | None = None
    cancel_sent: float | None = None  # when the controller last sent it to the cell
    cancel_sends: int = 0
    held_parts: tuple[str, ...] = ()  # the ids of its parts held now (``held`` counts them)
    due: float | None = None  # when it is due (unix s; None: no due time), sent with it

    @property
    def cancelling(self) -> bool:
        """A cancel is on its way to the order's cell, not yet answered."""
        return self.cancel_asked is not None and self.state in OPEN_STATES

    @property
    def shown_state(self) -> str:
        """The state as a user reads it: ``cancelling`` while a cancel is on its way."""
        return CANCELLING if self.cancelling else self.state

    def as_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class CellSeen:
    """What the factory last heard from a cell."""

    name: str
    status: str  # online, offline, unknown
    status_time: float | None
    state: dict[str, Any] = field(default_factory=dict)
    state_time: float | None = None
    seq: int = 0
    epoch: str | None = None  # the mailbox whose reports seq counts

    @property
    def part_types(self) -> dict[str, float]:
        """Part types the cell makes, each with what one more part adds to its bound (s)."""
        types = self.state.get("part_types") or {}
        return {str(k): float((v or {}).get("bound_s", 0.0)) for k, v in types.items()}

    def out_of_service(self, part_type: str) -> list[str]:
        """The machines a part of ``part_type`` needs that are out of service now, by name
        (every machine of the cell counts as needed when its state does not say which)."""
        machines = self.state.get("machines") or {}
        needs = ((self.state.get("part_types") or {}).get(part_type) or {}).get("machines")
        return [
            name
            for name in (needs or machines)
            if not (machines.get(name) or {}).get("in_service", True)
        ]


@dataclass(frozen=True)
class FactoryEvent:
    id: int
    time: float
    cell: str | None
    order_id: str | None
    text: str


def order_of(row: sqlite3.Row) -> FactoryOrder:
    data = dict(row)
    data["refused"] = tuple(json.loads(data["refused"]))
    data["held_parts"] = tuple(json.loads(data.get("held_parts") or "[]"))
    return FactoryOrder(**data)


def cell_of(row: sqlite3.Row) -> CellSeen:
    state = json.loads(row["state"]) if row["state"] else {}
    return CellSeen(
        row["name"],
        row["status"],
        row["status_time"],
        state,
        row["state_time"],
        row["seq"],
        row["epoch"],
    )


class Taken(NamedTuple):
    """What one report did: ``text`` what changed, in words (or None); ``ask_after`` the seq
    after which the cell should send its reports again (None: nothing is missing); ``refused``
    why the report was not taken (or None)."""

    text: str | None = None
    ask_after: int | None = None
    refused: str | None = None


def log_event(
    db: sqlite3.Connection, now: float, cell: str | None, oid: str | None, text: str
) -> None:
    db.execute(
        "INSERT INTO events (time, cell, order_id, text) VALUES (?, ?, ?, ?)",
        (now, cell, oid, text),
    )
