"""What a mailbox is: orders in from the system level, reports out to it.

A backend implements :class:`Mailbox`; :func:`cellctl.mailbox.open_mailbox` picks one.
Every method that writes has made its write durable when it returns: a controller killed
right after ``post_report`` returns has still posted the report.
"""

from __future__ import annotations

import math
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Final, Self

from cellctl.cell.orders import ReportKind as ReportKind
from cellctl.errors import UsageError, check_printable

# Order states. An order moves forward only (see TRANSITIONS); ``held`` is the one state an
# order may leave and come back from, while the operator inspects one of its parts.
POSTED: Final = "posted"
ACCEPTED: Final = "accepted"
IN_PROGRESS: Final = "in-progress"
HELD: Final = "held"
DONE: Final = "done"
FAILED: Final = "failed"
CANCELLED: Final = "cancelled"

ORDER_STATES: Final = (POSTED, ACCEPTED, IN_PROGRESS, HELD, DONE, FAILED, CANCELLED)
#: States an order never leaves.
FINAL_STATES: Final = frozenset({DONE, FAILED, CANCELLED})
#: ``state -> states it may go to``. Setting the state an order already has is a no-op.
TRANSITIONS: Final[dict[str, frozenset[str]]] = {
    POSTED: frozenset({ACCEPTED, FAILED, CANCELLED}),
    ACCEPTED: frozenset({IN_PROGRESS, HELD, DONE, FAILED, CANCELLED}),
    IN_PROGRESS: frozenset({HELD, DONE, FAILED, CANCELLED}),
    HELD: frozenset({IN_PROGRESS, DONE, FAILED, CANCELLED}),
    DONE: frozenset(),
    FAILED: frozenset(),
    CANCELLED: frozenset(),
}

#: Report kinds, in the order they typically occur (the texts of :class:`ReportKind`).
REPORT_KINDS: Final = tuple(kind.value for kind in ReportKind)


@dataclass(frozen=True)
class Order:
    """One order: make ``qty`` parts of ``part_type``. Times are seconds since the epoch.

    Its due time, if it has one, is the mailbox's :meth:`Mailbox.due_times`: kept off these
    fields, as every record made of them field by field (the status' orders, which take no
    field they do not know) stays as it was."""

    id: str
    part_type: str
    qty: int
    priority: int
    state: str
    created: float
    updated: float
    note: str = ""


@dataclass(frozen=True)
class Report:
    """One report to the system level; ``seq`` grows by one per report, from 1."""

    seq: int
    time: float
    kind: str
    order_id: str | None
    part_id: str | None
    text: str
    data: dict[str, Any] = field(default_factory=dict)


def check_transition(order: Order, state: str) -> None:
    """Raise :class:`UsageError` unless ``order`` may go to ``state`` (or is there already)."""
    if state not in TRANSITIONS:
        raise UsageError(f"unknown order state {state!r} (known: {', '.join(ORDER_STATES)})")
    if state != order.state and state not in TRANSITIONS[order.state]:
        raise UsageError(f"order {order.id} is {order.state}: it cannot become {state}")


#: Most parts one order may ask for.
MAX_QTY: Final = 10_000
#: The integers SQLite stores (a larger one would fail at the write, not at the check).
INT64 = range(-(2**63), 2**63)


def check_new_order(part_type: str, qty: int, priority: int, order_id: str | None) -> str:
    """Validate a new order's fields; return its id (a fresh one if ``order_id`` is None)."""
    if not part_type.strip():
        raise UsageError("an order needs a part type")
    if qty < 1:
        raise UsageError(f"order quantity must be at least 1, not {qty}")
    if isinstance(priority, bool) or not isinstance(priority, int):
        raise UsageError(f"order priority must be a whole number, not {priority!r}")
    if priority not in INT64 or qty not in INT64:
        raise UsageError(f"order quantity and priority must fit in 64 bits: {qty}, {priority}")
    if order_id is None:
        return uuid.uuid4().hex[:12]
    if not order_id.strip() or order_id != order_id.strip() or any(c.isspace() for c in order_id):
        raise UsageError(f"order id {order_id!r} must be one word")
    # An escape sequence in an id would act on every operator's terminal that lists it.
    return check_printable(order_id, f"order id {order_id!r}")


#: The latest due time taken, unix seconds (the year 5138, as the factory's wire carries).
MAX_DUE: Final = 1e11


def check_due(due: float | None) -> float | None:
    """``due`` (unix seconds, or None: no due time) as a float; UsageError unless it is a
    finite time from 1970 to :data:`MAX_DUE`."""
    if due is None:
        return None
    if isinstance(due, bool) or not isinstance(due, int | float):
        raise UsageError(f"an order's due time is unix seconds, not {type(due).__name__}")
    if not (math.isfinite(due) and 0 <= due <= MAX_DUE):
        raise UsageError(f"an order's due time must be unix seconds from 0 to {MAX_DUE:.0f}")
    return float(due)


def check_report_kind(kind: str) -> None:
    """Raise :class:`UsageError` unless ``kind`` is one of :data:`REPORT_KINDS`."""
    if kind not in REPORT_KINDS:
        raise UsageError(f"unknown report kind {kind!r} (known: {', '.join(REPORT_KINDS)})")


class Mailbox(ABC):
    """Orders in, reports out. Use as a context manager, or call :meth:`close`.

    The poster chooses order ids, so posting the same order twice (after a lost
    acknowledgement, say) is harmless: the second post returns the first order unchanged
    (and its due time too).
    """

    @property
    @abstractmethod
    def epoch(self) -> str:
        """This mailbox's identity, made once when it was created: its reports' ``seq`` count
        from 1 within it, so a mailbox made anew is told apart from the one before."""

    @abstractmethod
    def post_order(
        self,
        part_type: str,
        qty: int = 1,
        priority: int = 0,
        order_id: str | None = None,
        *,
        due: float | None = None,
    ) -> tuple[Order, bool]:
        """Post an order, due at ``due`` (unix seconds, :func:`check_due`; None: no due
        time); return it and whether it is new (False: that id was posted before)."""

    @abstractmethod
    def due_times(self) -> dict[str, float]:
        """The due time of every order that has one, by order id (unix seconds)."""

    @abstractmethod
    def get_order(self, order_id: str) -> Order:
        """The order ``order_id``; :class:`UsageError` if there is none."""

    @abstractmethod
    def orders(self, states: Iterable[str] | None = None) -> list[Order]:
        """Orders (only those in ``states`` if given), highest priority first, then oldest."""

    def pending_orders(self) -> list[Order]:
        """Orders posted and not yet accepted or refused, in the order to take them."""
        return self.orders([POSTED])

    @abstractmethod
    def set_order_state(self, order_id: str, state: str, note: str = "") -> Order:
        """Move an order to ``state``; :class:`UsageError` for an illegal transition.

        Setting the state the order already has changes nothing but ``note`` (when given),
        so a controller that repeats the call after a restart does no harm; a new state
        takes ``note`` as its note, none when none is given.
        """

    @abstractmethod
    def post_report(
        self,
        kind: str,
        text: str,
        *,
        order_id: str | None = None,
        part_id: str | None = None,
        data: dict[str, Any] | None = None,
    ) -> Report:
        """Post a report of ``kind`` (one of :data:`REPORT_KINDS`); ``data`` must be JSON."""

    @abstractmethod
    def reports(self, since_seq: int = 0, limit: int | None = None) -> list[Report]:
        """Reports with ``seq > since_seq``, oldest first, at most ``limit`` of them."""

    @abstractmethod
    def close(self) -> None:
        """Release the backend's resources; the mailbox is unusable afterwards."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
