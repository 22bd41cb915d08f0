"""Orders into parts, parts' ends into orders, and the operator's word on service.

H's bookkeeping beside the scheduler: accepted orders become parts in the journal
(:meth:`OrderFlow.intake`), an alarm the operator cleared returns its machine to service
(:meth:`OrderFlow.sync_operator`), and each order's state follows its parts. The controller
owns one and hands it the world model and its log (:mod:`cellctl.cell.ports`)::

    orders = OrderFlow(world=controller, alarms=controller)
    orders.intake(); orders.sync_operator()
"""

from __future__ import annotations

from collections.abc import Hashable
from typing import TYPE_CHECKING

from cellctl.cell.commands import OPERATOR_OUT
from cellctl.cell.orders import ReportKind

if TYPE_CHECKING:
    from cellctl.cell.ports import AlarmSink, WorldModel

#: Where a part is once it has left the cell on the outfeed.
OUT = "out"


class OrderFlow:
    """Order and service bookkeeping of the controller (see module docstring)."""

    def __init__(self, world: WorldModel, alarms: AlarmSink) -> None:
        self.world = world
        self.log = alarms.log
        self._synced: Hashable = None  # what sync_operator last worked from
        self._taken: Hashable = None  # the mailbox's version intake last looked at
        self._closed: tuple[Hashable, bool] | None = None  # all_orders_closed, and when

    def version(self) -> Hashable:
        """Changes whenever the journal or the mailbox may have changed (None: a mailbox
        that cannot say, so always): what is worked out from both alone is worked out
        again only when this changed."""
        mailbox_version = getattr(self.world.mailbox, "version", None)
        if mailbox_version is None:
            return None
        return (self.world.journal.version, mailbox_version)

    def all_orders_closed(self) -> bool:
        """True when no order is open, or every open one waits for the operator (worked
        out again only once the journal or the mailbox changed)."""
        version = self.version()
        if version is not None and self._closed is not None and self._closed[0] == version:
            return self._closed[1]
        closed = self._all_closed()
        self._closed = (version, closed)
        return closed

    def _all_closed(self) -> bool:
        open_orders = self.world.mailbox.orders(states=["posted", "accepted", "in-progress"])
        if not open_orders:
            return True
        # Orders whose remaining parts are all held wait for the operator, not for us.
        for order in open_orders:
            parts = self.world.journal.parts(order_id=order.id)
            if not parts or any(p.status in ("waiting", "active") for p in parts):
                return False
        return True

    # -- intake: orders into parts ---------------------------------------------------------------

    def intake(self) -> None:
        """Accepted orders become parts in the journal; unknown part types are refused.

        Only orders posted since the last look can need it: with the mailbox unchanged since
        then, there is nothing to take.
        """
        mailbox = self.world.mailbox
        version = getattr(mailbox, "version", None)
        if version is not None and version == self._taken:
            return
        for order in mailbox.pending_orders():
            if order.part_type not in self.world.config.parts:
                mailbox.set_order_state(order.id, "failed", f"unknown part {order.part_type}")
                self.world.mailbox.post_report(
                    ReportKind.ORDER_REJECTED,
                    f"order {order.id}: no part type {order.part_type!r} in this cell",
                    order_id=order.id,
                )
                continue
            self.world.journal.create_parts(order)
            self.world.mailbox.set_order_state(order.id, "accepted")
            self.world.mailbox.post_report(
                ReportKind.ORDER_ACCEPTED,
                f"order {order.id}: {order.qty} x {order.part_type}",
                order_id=order.id,
            )
            self.log(f"order {order.id} accepted: {order.qty} x {order.part_type}")
        # The version from before this look's own writes: the next look reads once more, and
        # finds nothing posted.
        self._taken = version

    def sync_operator(self) -> None:
        """A machine's out-of-service alarm the operator cleared puts it back in service (not
        one the operator took out: only the operator returns that).

        Its answer follows from the journal, the mailbox and the machines' service alone:
        when none of them changed since the last call, there is nothing to do.
        """
        version = self.version()
        basis = (version, tuple(v.in_service for v in self.world.machines.values()))
        if version is not None and basis == self._synced:
            return
        out = self.world.journal.machines_out_of_service()
        # Only its out-of-service alarm holds it out: the fault's own alarm (a readiness it
        # lost) returns once recovery, which leaves a machine out of service alone, sets it
        # up again; waiting for that alarm too would hold it out for good.
        held_out = {
            a.machine for a in self.world.journal.active_alarms() if a.code == "out-of-service"
        }
        for name, view in self.world.machines.items():
            if name in out and out[name].startswith(OPERATOR_OUT):
                view.in_service = False
            elif name in out and name not in held_out:
                self.world.journal.set_machine_service(name, True, "alarm cleared by the operator")
                view.in_service = True
                view.failures = 0
                self.log(f"{name}: back in service")
            elif name not in out:
                view.in_service = True
        # A part the operator found on the outfeed (released there after an interrupted
        # unload) with its whole route machined is done.
        types = self.world.config.parts
        for p in self.world.journal.parts(statuses=["waiting"]):
            if p.location == OUT and p.route_index >= len(types[p.part_type].route):
                self.world.journal.finish_part(p.id)
                self.log(f"part {p.id} done (released on the outfeed)")
        self._update_orders()
        self._synced = basis  # only once all of it is done: a failure is retried

    def _update_orders(self) -> None:
        for order in self.world.mailbox.orders(states=["accepted", "in-progress", "held"]):
            parts = self.world.journal.parts(order_id=order.id)
            if not parts:
                continue
            statuses = [p.status for p in parts]
            if all(s in ("done", "scrapped") for s in statuses):
                made = statuses.count("done")
                if made:
                    note = f"{made} made" + (
                        f", {statuses.count('scrapped')} scrapped" if "scrapped" in statuses else ""
                    )
                    self.world.mailbox.set_order_state(order.id, "done", note)
                    self.world.mailbox.post_report(
                        ReportKind.ORDER_DONE, f"order {order.id} done: {note}", order_id=order.id
                    )
                    self.log(f"order {order.id} done ({note})")
                else:
                    self.world.mailbox.set_order_state(order.id, "failed", "every part scrapped")
                    self.world.mailbox.post_report(
                        ReportKind.ORDER_FAILED,
                        f"order {order.id}: every part scrapped",
                        order_id=order.id,
                    )
            elif "held" in statuses and order.state != "held":
                self.world.mailbox.set_order_state(order.id, "held", "a part needs the operator")
            elif ("held" not in statuses and order.state == "held") or (
                order.state == "accepted"
                and any(p.status != "waiting" or p.route_index for p in parts)
            ):
                self.world.mailbox.set_order_state(order.id, "in-progress")
