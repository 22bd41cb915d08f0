"""Cancelling an order at the factory, and an order no cell can ever make, without a broker:
the store's cancels and the cell's answers to them, the cell's side of the bridge cancelling
through the control API's own ``orders.cancel``, the cancel message's strict model, and what
the dispatch calls waiting and what it calls never. The runs over a real broker, real cells
and ``cellctl factory`` are in tests/test_factory_edges.py
(``test_the_factory_command_line_on_a_running_plant``)."""

from __future__ import annotations

import asyncio
import json
import re
import shutil
import sqlite3
import tempfile
import time
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.errors import UsageError
from cellctl.factory.cancel import cell_canceller, request_cancel
from cellctl.factory.dispatch import stuck
from cellctl.factory.store import SCHEMA, FactoryStore
from cellctl.mailbox.wire import (
    MAX_REASON,
    CancelMessage,
    ReportMessage,
    WireError,
    parse_report,
    parse_to_cell,
)
from cellctl.service.access import LocalCell
from cellctl.service.audit import AuditLog
from cellctl.service.methods import Dispatcher
from tests.test_factory_units import bridge_of

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell"
EPOCH = "0123456789abcdef"
BASE = "wax-robot-base"


def report(seq: int, kind: str, order_id: str, **more: Any) -> ReportMessage:
    fields = {"cell": "cell1", "epoch": EPOCH, "seq": seq, "kind": kind, "order_id": order_id}
    return parse_report(json.dumps({"v": 1, "text": kind, "time": 1.0, **fields, **more}).encode())


def state(*types: str) -> dict[str, Any]:
    part_types = {t: {"bound_s": 10.0} for t in types}
    return {"v": 1, "part_types": part_types, "finish_estimate_s": 0.0, "time": 100.0}


@pytest.fixture
def store(tmp_path: Path) -> FactoryStore:
    return FactoryStore(tmp_path / "state" / "factory.db")


def texts(store: FactoryStore, oid: str) -> list[str]:
    return [e.text for e in store.events() if e.order_id == oid]


# -- the factory's store -------------------------------------------------------------------------


def test_a_queued_order_is_cancelled_at_once_and_an_ended_or_unknown_one_refused(
    store: FactoryStore,
) -> None:
    store.submit(BASE, 2, order_id="Q")
    asked = request_cancel(store, "Q", reason="ordered twice", by="ann")
    assert asked.message == "order Q cancelled (it was at no cell)"
    q = store.get("Q")
    assert (q.state, q.shown_state, q.note) == (
        "cancelled",
        "cancelled",
        "cancelled by ann: ordered twice",
    )
    assert texts(store, "Q")[-1] == "order Q cancelled by ann: ordered twice (at no cell)"
    with pytest.raises(UsageError, match="order Q is cancelled: there is nothing to cancel"):
        request_cancel(store, "Q", by="ann")
    with pytest.raises(UsageError, match="no order 'NOPE' in the factory"):
        request_cancel(store, "NOPE", by="ann")
    store.submit(BASE, 1, order_id="D")
    store.send("D", "cell1", expires=time.time() + 30)
    store.take_report("cell1", report(1, "order-done", "D"))
    before = texts(store, "D")
    with pytest.raises(UsageError, match="order D is done"):
        request_cancel(store, "D", by="ann")
    assert texts(store, "D") == before and store.get("D").cancel_asked is None
    with pytest.raises(UsageError, match=f"at most {MAX_REASON}"):
        store.cancel("D", by="ann", reason="x" * (MAX_REASON + 1))


def test_an_order_at_a_cell_is_cancelling_until_its_cell_answers(store: FactoryStore) -> None:
    store.submit(BASE, 2, order_id="A")
    store.send("A", "cell1", expires=time.time() + 30)
    asked = request_cancel(store, "A", reason="wrong stock", by="ann")
    assert "cancelling at cell1" in asked.message
    a = store.get("A")
    assert (a.state, a.shown_state, a.cancel_by, a.cancel_reason) == (
        "sent",
        "cancelling",
        "ann",
        "wrong stock",
    )
    assert [o.id for o in store.cancelling()] == ["A"]
    # Asked again while on its way: nothing changes, nothing more is logged.
    again = request_cancel(store, "A", reason="other", by="bob")
    assert "already on its way to cell1 (asked by ann at" in again.message
    assert store.get("A") == a
    assert sum("cancel asked" in t for t in texts(store, "A")) == 1
    store.cancel_sent("A")
    store.cancel_sent("A")
    assert store.get("A").cancel_sends == 2
    assert texts(store, "A").count("order A: cancel sent to cell1") == 1
    # The cell's reports go on moving the order; it stays cancelling until the answer.
    store.take_report("cell1", report(1, "order-accepted", "A"))
    assert (store.get("A").state, store.get("A").shown_state) == ("accepted", "cancelling")
    store.take_report("cell1", report(2, "order-cancelled", "A", text="order A cancelled"))
    done = store.get("A")
    assert (done.state, done.shown_state) == ("cancelled", "cancelled")
    assert done.note == "order A cancelled (asked by ann: wrong stock)"
    assert store.cancelling() == []


def test_a_refused_cancel_lets_the_order_go_on(store: FactoryStore) -> None:
    store.submit(BASE, 1, order_id="R")
    store.send("R", "cell1", expires=time.time() + 30)
    store.take_report("cell1", report(1, "order-accepted", "R"))
    store.take_report("cell1", report(2, "step-started", "R"))
    store.cancel("R", by="ann")
    asked = store.get("R").cancel_asked
    assert asked is not None
    # An answer to another request (one withdrawn before) changes nothing.
    store.take_report("cell1", report(3, "cancel-refused", "R", data={"asked": asked - 1}))
    assert store.get("R").shown_state == "cancelling"
    words = "order R is in-progress: only an order that has not started can be cancelled"
    taken = store.take_report(
        "cell1", report(4, "cancel-refused", "R", text=words, data={"asked": asked, "by": "ann"})
    )
    assert taken.text == f"order R: cell1 did not cancel it: {words}"
    r = store.get("R")
    assert (r.state, r.shown_state, r.cancel_asked) == ("in-progress", "in-progress", None)
    assert r.note == f"cell1 did not cancel it: {words}"
    store.take_report("cell1", report(5, "order-done", "R"))
    assert store.get("R").state == "done"


def test_a_sent_order_refused_while_cancelling_is_cancelled_not_sent_elsewhere(
    store: FactoryStore,
) -> None:
    store.submit(BASE, 1, order_id="S")
    store.send("S", "cell1", expires=time.time() + 30)
    store.cancel("S", by="ann")
    store.requeue("S", "cell1", "went offline")  # a cancel on its way keeps it where it is
    assert store.get("S").state == "sent"
    store.take_report("cell1", report(1, "order-rejected", "S", text="expired"))
    s = store.get("S")
    assert (s.state, s.cell, s.note) == (
        "cancelled",
        "cell1",
        "cancelled: cell1 refused it (expired)",
    )
    # Ended before the cancel came: it ends as it did, and says so.
    store.submit(BASE, 1, order_id="T")
    store.send("T", "cell1", expires=time.time() + 30)
    store.cancel("T", by="ann")
    store.take_report("cell1", report(2, "order-done", "T", text="order T done: 1 made"))
    assert store.get("T").note == "order T done: 1 made (it ended before the cancel came)"
    # Past its deadline at a cell gone away: cancelled here.
    store.submit(BASE, 1, order_id="U")
    store.send("U", "cell1", expires=time.time() - 1)
    store.cancel("U", by="ann")
    assert store.cancel_here("U", "cell1 went offline and did not take it in time")
    assert store.get("U").state == "cancelled"
    # ... and if that cell has started it after all, that is said loudly.
    loud = store.take_report("cell1", report(3, "cancel-refused", "U", text="started"))
    assert loud.text == "order U was cancelled here, but cell1 makes it: started"


def test_an_order_chosen_then_cancelled_from_the_command_line_is_not_sent(
    store: FactoryStore,
) -> None:
    store.submit(BASE, 1, order_id="C")
    store.submit(BASE, 1, order_id="K")
    store.cancel("C", by="ann")  # between the controller's look and its commit
    sent = store.send_many([("C", "cell1"), ("K", "cell1")], time.time() + 30)
    assert [o.id for o in sent] == ["K"] and store.get("C").state == "cancelled"


def old_store(path: Path, schema: str) -> None:
    """A factory store made with an older ``schema``, holding one queued order, OLD."""
    with sqlite3.connect(path) as db:
        db.executescript(schema)
        db.execute(
            "INSERT INTO orders (id, part_type, qty, priority, state, submitted, updated)"
            " VALUES ('OLD', 'wax-robot-base', 1, 0, 'queued', 1.0, 1.0)"
        )
    db.close()


def test_a_store_from_before_cancels_is_opened_and_kept(tmp_path: Path) -> None:
    path = tmp_path / "factory.db"
    old = re.sub(
        r",\s+cancel_asked.*cancel_sends INTEGER NOT NULL DEFAULT 0", "", SCHEMA, flags=re.S
    )
    assert "cancel" not in old
    old_store(path, old)
    with FactoryStore(path) as store:
        assert store.get("OLD").cancel_asked is None
        store.cancel("OLD", by="ann")
        assert store.get("OLD").state == "cancelled"


# -- what can never be made ----------------------------------------------------------------------


def test_an_order_waits_for_a_cell_that_may_make_it_and_never_for_none(
    store: FactoryStore,
) -> None:
    cells = ["cell1", "cell2"]
    order, _ = store.submit("gear", 1, order_id="G")
    # Nothing heard yet: the cells may make it.
    assert stuck(order, store.cells(), cells) == (
        "no cell heard so far makes gear: waiting for cell1, cell2 to say what it makes",
        False,
    )
    store.set_state("cell1", state(BASE))
    store.set_status("cell1", "online")
    assert stuck(order, store.cells(), cells)[1] is False  # cell2 is still to be heard
    store.set_state("cell2", state(BASE, "wax-toy-mill-table"))
    store.set_status("cell2", "offline")
    assert stuck(order, store.cells(), cells) == (
        "no cell makes gear (the cells make: wax-robot-base, wax-toy-mill-table)",
        True,
    )
    # A cell that makes it and is offline: it comes back, the order waits for it.
    table, _ = store.submit("wax-toy-mill-table", 1, order_id="T")
    assert stuck(table, store.cells(), cells) == (
        "waiting for a cell that makes wax-toy-mill-table to come online (cell2)",
        False,
    )
    # Refused by the one cell that makes it: never (the others' refusals are not needed).
    store.set_status("cell2", "online")
    store.send("T", "cell2", expires=time.time() + 30)
    store.take_report("cell2", report(1, "order-rejected", "T", text="no such part"))
    why, never = stuck(store.get("T"), store.cells(), cells)
    assert never and why == (
        "refused by every cell that makes wax-toy-mill-table (cell2: no such part)"
    )


# -- the cancel message ----------------------------------------------------------------------------

CANCEL = {"v": 1, "cancel": "order", "id": "F7", "by": "ann", "reason": "", "asked": 1.7e9}


def test_the_cancel_message_is_read_strictly() -> None:
    message = parse_to_cell(json.dumps(CANCEL).encode())
    assert isinstance(message, CancelMessage) and message.id == "F7"
    assert parse_to_cell(message.model_dump_json().encode()) == message
    for bad, why in (
        ({**CANCEL, "qty": 1}, "Extra inputs"),
        ({**CANCEL, "cancel": "part"}, "cancel"),
        ({**CANCEL, "by": ""}, "by"),
        ({**CANCEL, "reason": "x" * (MAX_REASON + 1)}, "reason"),
        ({**CANCEL, "asked": "now"}, "asked"),
        ({**CANCEL, "id": 7}, "id"),
        ({k: v for k, v in CANCEL.items() if k != "asked"}, "asked"),
    ):
        with pytest.raises(WireError, match=why):
            parse_to_cell(json.dumps(bad).encode())


_ANY = st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8)


@settings(max_examples=80, deadline=None)
@given(
    st.fixed_dictionaries(
        {"v": st.just(1) | _ANY, "cancel": st.just("order") | _ANY},
        optional={"id": st.text(max_size=4) | _ANY, "by": _ANY, "reason": _ANY, "asked": _ANY},
    )
)
def test_any_cancel_like_message_is_a_cancel_or_a_wire_error(payload: dict[str, Any]) -> None:
    try:
        message = parse_to_cell(json.dumps(payload).encode())
    except WireError:
        return
    assert isinstance(message, CancelMessage)


# -- the cell's side: its own cancel, through its control API --------------------------------------


async def test_the_cell_cancels_as_its_operator_would_and_answers_each_request_once(
    tmp_path: Path,
) -> None:
    cell_dir = tmp_path / "cell"
    shutil.copytree(EXAMPLE, cell_dir)
    api = Dispatcher(LocalCell(cell_dir, {}))
    bridge, mailbox, journal = bridge_of(cell_dir, cancel=cell_canceller(api))
    with mailbox, journal:

        def taken(oid: str) -> None:
            """The order arrives and the controller takes it in (as its intake does)."""
            order = {"v": 1, "id": oid, "part_type": BASE, "qty": 2}
            bridge.take_order(json.dumps(order).encode())
            journal.create_parts(mailbox.get_order(oid))
            mailbox.set_order_state(oid, "accepted")

        async def cancel(oid: str, asked: float, reason: str = "") -> list[tuple[str, str]]:
            before = len(mailbox.reports())
            ask = {**CANCEL, "id": oid, "asked": asked, "reason": reason}
            bridge.take_order(json.dumps(ask).encode())
            await bridge.take_cancels()
            return [(r.kind, r.text) for r in mailbox.reports()[before:]]

        taken("A")
        assert await cancel("A", 1.0, "wrong stock") == [("order-cancelled", "order A cancelled")]
        a = mailbox.get_order("A")
        assert (a.state, a.note) == ("cancelled", "cancelled by the factory (ann): wrong stock")
        assert [p.status for p in journal.parts(order_id="A")] == ["cancelled"] * 2
        assert await cancel("A", 1.0) == []  # sent again: answered already
        assert await cancel("A", 2.0) == []  # a new request: its end is reported already
        # A part has started: the cell's own cancel refuses, and the factory hears why.
        taken("B")
        journal.begin_step(journal.parts(order_id="B")[0].id, "transfer", "robot", "x")
        (refused,) = await cancel("B", 3.0)
        assert refused[0] == "cancel-refused" and "has started" in refused[1]
        assert mailbox.reports()[-1].data == {"asked": 3.0, "by": "ann"}
        assert mailbox.get_order("B").state == "accepted"
        assert await cancel("B", 3.0) == []
        # Never reached the cell: nothing of it is made, and the factory is told.
        assert await cancel("NEVER", 4.0) == [
            ("order-cancelled", "order NEVER cancelled by the factory before it reached this cell")
        ]
        assert await cancel("NEVER", 4.0) == []
    api.close()
    # The cell's audit trail says who cancelled, through which method, and how it went.
    with AuditLog(cell_dir) as audit:
        entries = [(e.who, e.method, e.result) for e in audit.entries()]
    assert ("factory:ann", "orders.cancel", "ok") in entries
    assert any(who == "factory:ann" and "has started" in result for who, _, result in entries)


@settings(max_examples=30, deadline=None)
@given(
    st.lists(
        st.fixed_dictionaries(
            {
                "v": st.just(1),
                "cancel": st.just("order"),
                "id": st.sampled_from(["A", "B", "gone"]) | st.text(min_size=1, max_size=128),
                "by": st.text(min_size=1, max_size=128),
                "reason": st.text(max_size=MAX_REASON),
                "asked": st.floats(0, 1e11),
            }
        ),
        max_size=4,
    )
)
def test_the_cell_takes_any_cancel_the_factory_may_send(asks: list[dict[str, Any]]) -> None:
    """Whatever valid cancel comes (an id it has or not, any name and reason), the cell
    answers it with a report or nothing, and its link goes on: no other exception."""
    with tempfile.TemporaryDirectory() as tmp:
        cell_dir = Path(tmp) / "cell"
        shutil.copytree(EXAMPLE, cell_dir)
        api = Dispatcher(LocalCell(cell_dir, {}))
        bridge, mailbox, journal = bridge_of(cell_dir, cancel=cell_canceller(api))
        with mailbox, journal:
            for oid in ("A", "B"):
                order = {"v": 1, "id": oid, "part_type": BASE, "qty": 1}
                bridge.take_order(json.dumps(order).encode())
            journal.create_parts(mailbox.get_order("B"))
            journal.begin_step(journal.parts(order_id="B")[0].id, "transfer", "robot", "x")

            async def main() -> None:
                for ask in asks:
                    bridge.take_order(json.dumps(ask).encode())
                    await bridge.take_cancels()

            asyncio.run(main())
            kinds = {r.kind for r in mailbox.reports()}
            assert kinds <= {"order-cancelled", "cancel-refused"}
            assert mailbox.get_order("B").state != "cancelled"  # it has started
        api.close()
