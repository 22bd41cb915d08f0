"""A running cell's state as a plan's inputs: what is left of each open order, where its parts
are, and how far a cut in flight has gone (in machine seconds: an emulated cell's time
scale counts)."""

from __future__ import annotations

from pathlib import Path

from cellctl.cell.journal import open_journal
from cellctl.clock import RealClock
from cellctl.mailbox import open_mailbox
from cellctl.plan.engine import HeldPart, PartAt, PlanOrder
from cellctl.plan.snapshot import open_work


class Clock(RealClock):
    """A clock the test sets: the journal's times are exact."""

    def __init__(self) -> None:
        super().__init__()
        self.at = 1000.0

    def now(self) -> float:
        return self.at


def test_a_cut_in_flight_is_taken_up_as_far_as_it_has_gone(tmp_path: Path) -> None:
    clock = Clock()
    with open_journal(tmp_path, clock=clock) as journal, open_mailbox(tmp_path) as mailbox:
        order, _ = mailbox.post_order("wax-robot-base", 4, order_id="A")
        mailbox.set_order_state("A", "accepted")
        cutting, carried, held, waiting = journal.create_parts(order)
        # One part roughed and cut at cnc2 for 12 s of the cell's clock now; one roughed,
        # its transfer to cnc2 in flight; one held at cnc1; one still on the conveyor.
        journal.move_part(cutting.id, "cnc2", 1)
        journal.begin_step(cutting.id, "machine", "cnc2", "robot_base_finish_cnc2")
        journal.move_part(carried.id, "cnc1", 1)
        journal.begin_step(carried.id, "transfer", "robot", "cnc1_to_cnc2")
        journal.move_part(held.id, "cnc1", 0)
        journal.hold_part(held.id, "needs inspection")
        clock.at += 12.0
        orders, parts_held = open_work(mailbox, journal, time_scale=100.0)
        assert orders == (
            PlanOrder(
                "A",
                "wax-robot-base",
                3,
                under_way=(PartAt("cnc2", 1, done_s=1200.0), PartAt("cnc1", 1, done_s=0.0)),
            ),
        )
        assert parts_held == (HeldPart("A", "wax-robot-base", "cnc1", 0),)
        # Counted to the time given (a real cell's: machine seconds are its seconds).
        orders, _ = open_work(mailbox, journal, now=clock.at - 2.0)
        assert orders[0].under_way[0].done_s == 10.0
        assert waiting.location == "conveyor"
