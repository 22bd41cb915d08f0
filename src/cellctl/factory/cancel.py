"""Cancelling an order of the factory: ``cellctl factory cancel ORDER [--reason TEXT]``.

::

    with FactoryStore(config.state_path) as store:
        asked = request_cancel(store, "F7", reason="wrong material")   # who: this user
        print(asked.message)

An order at no cell (``queued``) is cancelled in the store at once. An order given to a cell
is cancelled by that cell: the store keeps the request (the order shows as ``cancelling``),
and ``cellctl factory run`` sends it on the cell's ``orders`` topic
(:class:`~cellctl.mailbox.wire.CancelMessage`) every ``resend`` seconds until the cell's
answer comes: ``order-cancelled`` (the order is ``cancelled``) or ``cancel-refused`` (the
cell's own cancel refuses an order of which a part has started: the order goes on, and its
note says why). Either way the request and its end are in the factory's events. A done,
failed or cancelled order, or an unknown id, is refused before anything is recorded.

On the cell, :func:`cell_canceller` is what ``cellctl run`` gives its MQTT bridge: the control
API's own ``orders.cancel``, called as ``factory:WHO`` (an operator), so the cell cancels as
its operator's cancel does and its audit trail says who asked.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING

from cellctl.factory.store import ACCEPTED, SENT, FactoryOrder, FactoryStore
from cellctl.mailbox.wire import MAX_NAME
from cellctl.service.rpc import login_name

if TYPE_CHECKING:  # the cell's side: imported where the cell runs, not by every command
    from cellctl.mailbox.mqtt import Canceller
    from cellctl.service.methods import Dispatcher


def local_user() -> str:
    """Who runs this command, as the cell's audit trail will name them (``factory:WHO``)."""
    return login_name()[:MAX_NAME]


@dataclass(frozen=True)
class CancelAsked:
    """What ``cellctl factory cancel`` did: ``order`` as it is now, and ``message`` to print."""

    order: FactoryOrder
    message: str


def request_cancel(
    store: FactoryStore, order_id: str, *, reason: str = "", by: str | None = None
) -> CancelAsked:
    """Cancel ``order_id`` (queued: at once; at a cell: through it); UsageError for an order
    that has ended or does not exist. Asking again while a cancel is on its way changes
    nothing."""
    by = by or local_user()
    order, outcome = store.cancel(order_id, by=by, reason=reason)
    if outcome == "cancelled":
        return CancelAsked(order, f"order {order.id} cancelled (it was at no cell)")
    if outcome == "pending":
        when = datetime.fromtimestamp(order.cancel_asked or 0).strftime("%H:%M:%S")
        return CancelAsked(
            order,
            f"order {order.id}: a cancel is already on its way to {order.cell} "
            f"(asked by {order.cancel_by} at {when}); nothing sent again",
        )
    started = order.state not in (SENT, ACCEPTED)
    caveat = (
        f" (it has started there: {order.cell} cancels only an order none of whose parts "
        "has started, and says so if it cannot)"
        if started
        else ""
    )
    return CancelAsked(
        order,
        f"order {order.id}: cancelling at {order.cell}{caveat}; it is cancelled once "
        f"{order.cell} says so (`cellctl factory run` tells it)",
    )


def cell_canceller(dispatcher: Dispatcher) -> Canceller:
    """The factory's cancel of an order, on the cell: the control API's ``orders.cancel``
    through ``dispatcher`` (``cellctl run``'s own), as the operator ``factory:WHO``."""

    from cellctl.service.rpc import Caller

    async def cancel(order_id: str, by: str) -> str:
        caller = Caller(f"factory:{by}", "operator")
        result = await dispatcher.call("orders.cancel", {"id": order_id}, caller=caller)
        return str(result["message"])

    return cancel
