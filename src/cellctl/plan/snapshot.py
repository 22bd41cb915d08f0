"""A running cell's state now, as a plan's inputs: what ``plan.run`` plays forward on a copy.

::

    orders, held = open_work(mailbox, journal)   # orders not finished, parts held now
    out = sorted(journal.machines_out_of_service())

Each order not finished (posted, accepted, in progress, held) is played with what remains
of it: its quantity less the parts done, scrapped, cancelled and held. A held part stays held
where it is (:class:`~cellctl.plan.engine.HeldPart`): the plan does not guess the operator's
word on it. A part on its way is taken up where it is (``PlanOrder.under_way``): at a mill
with the cuts it has, the plan goes on with it as the controller would after a restart. A
cut in flight now is taken up as far as it has gone (``PartAt.done_s``: the time since its
step began, in machine seconds); a transfer in flight is played again whole (seconds).

A cell no controller runs is read from copies (:func:`copied_stores`; the control API's
``LocalCell.work_to_plan``): a plan writes nothing into the cell it plans, not even a
mailbox where there is none::

    with copied_stores(cell_dir) as (mailbox, journal):
        orders, held = open_work(mailbox, journal)
"""

from __future__ import annotations

import contextlib
import shutil
import sqlite3
import tempfile
from collections.abc import Iterator
from pathlib import Path

from cellctl.cell.config import CONVEYOR
from cellctl.cell.journal import JOURNAL_FILE, Journal, open_journal
from cellctl.cell.sqlitedb import refuse_links
from cellctl.errors import UsageError
from cellctl.mailbox import MAILBOX_FILE, Mailbox
from cellctl.mailbox.sqlite import SqliteMailbox
from cellctl.plan.engine import HeldPart, PartAt, PlanOrder

#: The least ``done_s`` of a cut in flight (one just begun): more than 0, as a plan tells
#: a cut in flight from a part waiting to be cut (a machine out of service finishes the one).
IN_FLIGHT_S = 0.001
#: Order states still to be worked on.
OPEN_STATES = ("posted", "accepted", "in-progress", "held")


def open_work(
    mailbox: Mailbox, journal: Journal | None, *, now: float | None = None, time_scale: float = 1.0
) -> tuple[tuple[PlanOrder, ...], tuple[HeldPart, ...]]:
    """The orders still to make (their remaining quantities) and the parts held now.

    ``now``: the cell's clock now (default: the journal's), what a cut in flight has done is
    counted to; ``time_scale``: the cell's (``[cell] time_scale``: an emulated cell's
    machines run that many times faster than the plan's)."""
    orders: list[PlanOrder] = []
    held: list[HeldPart] = []
    cutting: dict[str, float] = {}  # part id -> when its cut in flight began
    if journal is not None:
        cutting = {s.part_id: s.started for s in journal.open_steps() if s.kind == "machine"}
        now = journal.clock.now() if now is None else now
    for order in mailbox.orders(states=list(OPEN_STATES)):
        parts = journal.parts(order_id=order.id) if journal is not None else []
        settled = sum(p.status in ("done", "scrapped", "cancelled", "held") for p in parts)
        for p in parts:
            if p.status == "held":
                held.append(HeldPart(order.id, p.part_type, p.location, p.route_index))
        under_way = tuple(
            PartAt(p.location, p.route_index, _done(cutting.get(p.id), now, time_scale))
            for p in parts
            if p.status in ("waiting", "active") and (p.location != CONVEYOR or p.route_index)
        )
        remaining = order.qty - settled
        if remaining > 0:
            orders.append(
                PlanOrder(order.id, order.part_type, remaining, order.priority, under_way=under_way)
            )
    return tuple(orders), tuple(held)


def _done(since: float | None, now: float | None, time_scale: float) -> float:
    """Machine seconds of a cut begun at ``since`` done by ``now`` (0: none in flight; a
    cut in flight has done at least :data:`IN_FLIGHT_S`: ``done_s`` > 0 says it is)."""
    if since is None or now is None:
        return 0.0
    return max(IN_FLIGHT_S, round(max(0.0, now - since) * time_scale, 3))


def out_of_service(journal: Journal | None) -> tuple[str, ...]:
    """The machines out of automatic service now (the journal's record of it)."""
    return tuple(sorted(journal.machines_out_of_service())) if journal is not None else ()


def copy_store(source: Path, target: Path) -> bool:
    """Copy the SQLite file ``source`` (a cell's mailbox or journal) to ``target``, reading
    it only: nothing is made beside it. False if there is no such file."""
    refuse_links(source)  # read through a link, it would copy whatever file it names
    if not source.is_file():
        return False
    # A read-only connection to a file in WAL mode makes its -wal and -shm when they are
    # missing, and leaves them. With no -wal, no writer has the file open and every commit is
    # in it: it is read as immutable (no locks, no side files). With one (a writer has it
    # open, or one ended without its last checkpoint), the side files are there already,
    # and a read-only connection reads the commits in the -wal too.
    wal = source.with_name(source.name + "-wal")
    mode = "ro" if wal.exists() else "ro&immutable=1"
    try:
        original = sqlite3.connect(f"{source.resolve().as_uri()}?mode={mode}", uri=True)
        try:
            copy = sqlite3.connect(target)
            try:
                original.backup(copy)
            finally:
                copy.close()
        finally:
            original.close()
    except sqlite3.Error as e:
        raise UsageError(f"{source}: could not read it ({e})") from None
    return True


@contextlib.contextmanager
def copied_stores(cell_dir: Path) -> Iterator[tuple[Mailbox, Journal | None]]:
    """A cell's mailbox and journal copied (:func:`copy_store`) into a scratch directory of
    their own and opened there, removed when the context ends: a plan of a cell no
    controller runs reads these, so that it writes nothing into the cell it plans. The
    journal is None if the cell has none (it never ran); a cell with no mailbox reads as one
    with no orders."""
    with contextlib.ExitStack() as stack:
        scratch = Path(tempfile.mkdtemp(prefix="cellctl-plan-files-"))
        stack.callback(shutil.rmtree, scratch, ignore_errors=True)
        copy_store(cell_dir / MAILBOX_FILE, scratch / MAILBOX_FILE)
        has_journal = copy_store(cell_dir / JOURNAL_FILE, scratch / JOURNAL_FILE)
        mailbox = SqliteMailbox(scratch / MAILBOX_FILE, durable=False)
        stack.callback(mailbox.close)
        journal = open_journal(scratch, durable=False) if has_journal else None
        if journal is not None:
            stack.callback(journal.close)
        yield mailbox, journal
