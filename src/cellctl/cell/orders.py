"""What the controller needs of a mailbox, said here so the cell does not depend on one.

The layers run errors → link → protocol → drivers/emulators → cell → mailbox → ui: a mailbox
backend (``cellctl.mailbox``) fits these protocols, the cell never imports it.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from enum import StrEnum
from typing import Any, Protocol


class ReportKind(StrEnum):
    """What a report says happened, in the order reports typically occur. A member is its
    text (``ReportKind.ORDER_DONE == "order-done"``): the mailbox stores and sends the text."""

    ORDER_ACCEPTED = "order-accepted"
    ORDER_REJECTED = "order-rejected"
    STEP_STARTED = "step-started"
    STEP_FINISHED = "step-finished"
    STEP_FAILED = "step-failed"
    ALARM_RAISED = "alarm-raised"
    ALARM_CLEARED = "alarm-cleared"
    PART_HELD = "part-held"
    PART_RELEASED = "part-released"
    PART_SCRAPPED = "part-scrapped"
    ORDER_DONE = "order-done"
    ORDER_FAILED = "order-failed"
    ORDER_CANCELLED = "order-cancelled"
    #: The factory asked the cell to cancel an order the cell's own cancel refuses (a part
    #: has started): the order goes on; ``data`` names the request (``asked``, ``by``).
    CANCEL_REFUSED = "cancel-refused"


class OrderLike(Protocol):
    """What the journal needs of an order to make its parts."""

    @property
    def id(self) -> str: ...
    @property
    def part_type(self) -> str: ...
    @property
    def qty(self) -> int: ...


class OrderView(OrderLike, Protocol):
    """An order as the controller reads it (``cellctl.mailbox.Order`` fits)."""

    @property
    def priority(self) -> int: ...
    @property
    def state(self) -> str: ...
    @property
    def created(self) -> float: ...


class OrderBox(Protocol):
    """Orders in, reports out (``cellctl.mailbox.Mailbox`` fits)."""

    def orders(self, states: Iterable[str] | None = None) -> Sequence[OrderView]: ...
    def pending_orders(self) -> Sequence[OrderView]: ...
    def set_order_state(self, order_id: str, state: str, note: str = "") -> Any: ...
    def post_report(
        self,
        kind: str,
        text: str,
        *,
        order_id: str | None = None,
        part_id: str | None = None,
        data: dict[str, Any] | None = None,
    ) -> Any: ...
