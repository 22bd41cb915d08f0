"""The factory's parts without a broker: factory.toml, the store following an order through
its cell's reports, the choice of a cell, and a cell that takes back an acceptance it could
not report before the order expired (the end-to-end runs are in tests/test_factory.py)."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from cellctl.cell.config import CellConfig, load_cell
from cellctl.cell.journal import open_journal
from cellctl.errors import UsageError
from cellctl.factory.config import load_factory
from cellctl.factory.dispatch import choose, every_cell_refused, load_s
from cellctl.factory.store import FactoryStore
from cellctl.mailbox import open_mailbox
from cellctl.mailbox.mqtt import Canceller, MqttBridge, MqttSettings
from cellctl.mailbox.wire import ReportMessage, parse_report

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell"
FACTORY_TOML = """
[factory]
name = "lab"
accept_timeout = 12

[broker]
url = "mqtt://127.0.0.1:1883"
credentials = "factory.credentials"

[cells.cell1]
prefix = "cellctl/cell1"

[cells.cell2]
prefix = "cellctl/cell2"
"""


def state(bounds: dict[str, float], finish: float = 0.0, **more: Any) -> dict[str, Any]:
    types = {name: {"bound_s": b} for name, b in bounds.items()}
    return {"v": 1, "part_types": types, "finish_estimate_s": finish, "time": 100.0, **more}


EPOCH = "0123456789abcdef"


def report(seq: int, kind: str, order_id: str, **more: Any) -> ReportMessage:
    fields = {"cell": "c", "epoch": EPOCH, "seq": seq, "kind": kind, "order_id": order_id}
    return parse_report(json.dumps({"v": 1, "text": kind, "time": 1.0, **fields, **more}).encode())


@pytest.fixture
def store(tmp_path: Path) -> FactoryStore:
    return FactoryStore(tmp_path / "state" / "factory.db")


def test_factory_toml_is_read_and_its_problems_named(tmp_path: Path) -> None:
    (tmp_path / "factory.toml").write_text(FACTORY_TOML)
    config = load_factory(tmp_path)
    assert config.cells == {"cell1": "cellctl/cell1", "cell2": "cellctl/cell2"}
    assert config.accept_timeout == 12 and config.resend == 2.0
    assert config.cell_url("cell2") == "mqtt://127.0.0.1:1883/cellctl/cell2"
    assert config.state_path == tmp_path / "state" / "factory.db"
    with pytest.raises(UsageError, match=r"no such file.*cellctl emulate factory"):
        load_factory(tmp_path / "nowhere")
    broken = FACTORY_TOML.replace('"cellctl/cell2"', '"cellctl/#"').replace("= 12", "= -1")
    (tmp_path / "factory.toml").write_text(broken)
    with pytest.raises(UsageError) as e:
        load_factory(tmp_path)
    assert "cells.cell2.prefix" in str(e.value) and "factory.accept_timeout" in str(e.value)
    (tmp_path / "factory.toml").write_text(FACTORY_TOML.replace("cellctl/cell2", "cellctl/cell1"))
    with pytest.raises(UsageError, match="same prefix"):
        load_factory(tmp_path)


def test_an_order_followed_through_its_cells_reports(store: FactoryStore) -> None:
    order, new = store.submit("wax-robot-base", 2, order_id="A")
    assert new and order.state == "queued"
    again, new = store.submit("wax-toy-mill-table", 5, order_id="A")
    assert not new and again.part_type == "wax-robot-base"  # the same id changes nothing
    with pytest.raises(UsageError, match="at least 1"):
        store.submit("wax-robot-base", 0)
    store.send("A", "cell1", expires=time.time() + 30)
    with pytest.raises(UsageError, match="is sent, not queued"):
        store.send("A", "cell2", expires=time.time() + 30)  # never dispatched twice
    steps = [
        (report(1, "order-accepted", "A", time=5.0), "accepted"),
        (report(2, "step-started", "A"), "in-progress"),
        (report(3, "part-held", "A"), "held"),
        (report(3, "part-held", "A"), "held"),  # the same report again: once
        (report(4, "part-released", "A"), "in-progress"),
        (report(5, "order-done", "A"), "done"),
    ]
    for r, expected in steps:
        store.take_report("cell1", r)
        assert store.get("A").state == expected, r
    done = store.get("A")
    assert (done.held, done.done, done.accepted) == (0, 2, 5.0)
    assert store.cells()["cell1"].seq == 5


def test_a_refusal_sends_the_order_elsewhere_a_late_one_may_come_back(store: FactoryStore) -> None:
    store.submit("wax-robot-base", 1, order_id="B")
    store.send("B", "cell1", expires=time.time() + 30)
    store.take_report("cell1", report(1, "order-rejected", "B", text="no such part"))
    back = store.get("B")
    assert (back.state, back.cell, back.refused) == ("queued", None, ("cell1",))
    assert every_cell_refused(back, ["cell1"]) and not every_cell_refused(back, ["cell1", "c2"])
    store.send("B", "cell2", expires=time.time() + 30)
    store.take_report("cell2", report(1, "order-rejected", "B", data={"expired": True}))
    assert store.get("B").refused == ("cell1",)  # too late is not "never"
    # An answer for an order that has moved on changes nothing, and is said when it accepts.
    store.send("B", "cell2", expires=time.time() + 30)
    store.take_report("cell2", report(2, "order-accepted", "B"))
    said = store.take_report("cell1", report(1, "order-accepted", "B")).text
    assert said == "order B accepted by cell1 too, after it went to cell2"
    assert store.get("B").cell == "cell2"


def test_the_earliest_estimated_finish_gets_the_order(store: FactoryStore) -> None:
    both = {"wax-robot-base": 10.0, "wax-toy-mill-table": 20.0}
    for name, finish in (("cell1", 50.0), ("cell2", 30.0), ("cell3", 0.0)):
        store.set_status(name, "online")
        store.set_state(name, state(both, finish))
    store.set_state("cell3", state({"wax-robot-base": 10.0}))  # makes one type only
    store.set_status("cell3", "offline")
    order, _ = store.submit("wax-robot-base", 3, order_id="C")
    cells = store.cells()
    # cell3 is offline; the why says what counted the finish.
    assert choose(order, cells, []) == ("cell2", "cell2 finishes it earliest by its bound: 60 s")
    # Orders sent and not yet in a cell's own estimate count against it.
    store.submit("wax-toy-mill-table", 2, order_id="D")
    store.send("D", "cell2", expires=time.time() + 30)
    open_orders = store.orders()
    assert load_s(cells["cell2"], open_orders) == 30.0 + 2 * 20.0
    assert choose(order, cells, open_orders)[0] == "cell1"
    table, _ = store.submit("wax-toy-mill-table", 1, order_id="E")
    store.set_status("cell1", "offline")
    store.set_status("cell2", "offline")
    assert choose(table, store.cells(), open_orders) == (
        None,
        "waiting for a cell that makes wax-toy-mill-table to come online",
    )
    odd, _ = store.submit("gear", 1, order_id="F")
    assert choose(odd, store.cells(), open_orders) == (None, "no cell makes gear")


def test_cells_alike_get_a_burst_of_mixed_orders_evenly(store: FactoryStore) -> None:
    bounds = {"wax-robot-base": 10.0, "wax-toy-mill-table": 10.0}
    for name in ("cell1", "cell2"):
        store.set_status(name, "online")
        store.set_state(name, state(bounds))
    for i, part in enumerate(["wax-robot-base", "wax-toy-mill-table"] * 2):
        order, _ = store.submit(part, 1, order_id=f"M{i}")
        cell, _ = choose(order, store.cells(), store.orders())
        assert cell is not None
        store.send(order.id, cell, expires=time.time() + 30)
    mix = {(o.cell, o.part_type) for o in store.orders()}
    assert len(mix) == 4  # each cell got one of each type, not two of one


def test_a_paused_cell_gets_an_order_only_when_no_other_can(store: FactoryStore) -> None:
    bounds = {"wax-robot-base": 10.0}
    store.set_status("cell1", "online")
    store.set_state("cell1", state(bounds, 0.0, paused=True))
    store.set_status("cell2", "online")
    store.set_state("cell2", state(bounds, 500.0))
    order, _ = store.submit("wax-robot-base", 1, order_id="G")
    assert choose(order, store.cells(), [])[0] == "cell2"
    store.set_status("cell2", "offline")
    assert choose(order, store.cells(), [])[0] == "cell1"


# -- a cell takes back an acceptance it could not report in time -------------------------------


@dataclass
class RunningCell:
    """What the bridge reads of a running controller (here: none runs)."""

    config: CellConfig
    machines: dict[str, Any] = field(default_factory=dict)
    paused: bool = False
    listeners: list[Any] = field(default_factory=list)
    pokes: int = 0

    def poke(self) -> None:
        self.pokes += 1


def bridge_of(cell_dir: Path, cancel: Canceller | None = None) -> tuple[MqttBridge, Any, Any]:
    """Cell ``cell1``'s MQTT bridge (never connected) over its mailbox and journal, which the
    caller closes; ``cancel``: how it cancels an order the factory asks it to."""
    (cell_dir / "mqtt.toml").write_text('username = "cell1"\npassword = "x"\n')
    (cell_dir / "mqtt.toml").chmod(0o600)
    settings = MqttSettings.load("mqtt://127.0.0.1:1/cellctl/cell1", cell_dir / "mqtt.toml")
    mailbox, journal = open_mailbox(cell_dir), open_journal(cell_dir)
    cell = RunningCell(load_cell(cell_dir))
    return MqttBridge(settings, cell, mailbox, journal, cancel=cancel), mailbox, journal


def take(bridge: MqttBridge, mailbox: Any, journal: Any, oid: str, expires: float) -> None:
    """The order arrives, and the controller takes it in (as its intake does)."""
    payload = {"v": 1, "id": oid, "part_type": "wax-robot-base", "qty": 1, "expires": expires}
    bridge.take_order(json.dumps(payload).encode())
    journal.create_parts(mailbox.get_order(oid))
    mailbox.set_order_state(oid, "accepted")
    mailbox.post_report("order-accepted", f"order {oid} accepted", order_id=oid)


def test_an_acceptance_not_reported_before_expiry_is_taken_back_unless_started(
    tmp_path: Path,
) -> None:
    cell_dir = tmp_path / "cell"
    shutil.copytree(EXAMPLE, cell_dir)
    bridge, mailbox, journal = bridge_of(cell_dir)
    # Far enough ahead that X and Y are taken in before it on a loaded box (an order that
    # comes expired is refused, not taken in), near enough to wait for.
    soon = time.time() + 2.0
    take(bridge, mailbox, journal, "X", soon)
    take(bridge, mailbox, journal, "Y", soon)
    (part,) = journal.parts(order_id="Y")
    journal.begin_step(part.id, "transfer", "robot", "conveyor_to_cnc1")  # Y has started
    take(bridge, mailbox, journal, "Z", time.time() + 60)
    assert set(bridge.expiring) == {"X", "Y", "Z"}
    time.sleep(max(0.0, soon - time.time()) + 0.1)  # past X's and Y's expiry
    # The cell is killed here and started again: the marks were saved with the orders.
    mailbox.close()
    journal.close()
    bridge, mailbox, journal = bridge_of(cell_dir)
    assert set(bridge.expiring) == {"X", "Y", "Z"}
    bridge.drop_expired()
    assert mailbox.get_order("X").state == "cancelled"
    assert [p.status for p in journal.parts(order_id="X")] == ["cancelled"]
    (taken_back,) = [
        r for r in mailbox.reports() if r.order_id == "X" and r.kind != "order-accepted"
    ]
    assert taken_back.kind == "order-rejected" and taken_back.data == {"expired": True}
    assert "expired before the factory heard it was accepted" in taken_back.text
    assert mailbox.get_order("Y").state == "accepted"  # started: it stays and is reported
    assert mailbox.get_order("Z").state == "accepted"  # not expired
    # Sent again by the factory: X is answered with the refusal, not the acceptance.
    bridge.sent_seq = max(r.seq for r in mailbox.reports())
    payload = {"v": 1, "id": "X", "part_type": "wax-robot-base", "qty": 1, "expires": soon}
    bridge.take_order(json.dumps(payload).encode())
    assert [r.kind for r in bridge._resend] == ["order-rejected"]


def test_an_order_come_expired_again_and_again_is_answered_once(tmp_path: Path) -> None:
    """A cell stopped (SIGSTOP) while the factory sent it an order finds every resend queued
    when it goes on, each past its expiry: one refusal, published again for each resend (an
    id it has seen changes nothing), not a refusal a resend."""
    cell_dir = tmp_path / "cell"
    shutil.copytree(EXAMPLE, cell_dir)
    bridge, mailbox, _ = bridge_of(cell_dir)
    payload = {"v": 1, "id": "D", "part_type": "wax-robot-base", "qty": 1, "expires": 1.0}
    for _ in range(5):
        bridge.take_order(json.dumps(payload).encode())
    said = [r for r in mailbox.reports() if r.order_id == "D"]
    assert [(r.kind, r.text) for r in said] == [("order-rejected", "order D: expired")]
    assert bridge._resend == []  # not published yet: it goes out once, as it is
    bridge.sent_seq = said[0].seq  # published
    bridge.take_order(json.dumps(payload).encode())
    assert bridge._resend == said
    assert [r.order_id for r in mailbox.reports()] == ["D"]


def test_reports_are_taken_in_order_per_mailbox_epoch(store: FactoryStore) -> None:
    store.submit("wax-robot-base", 1, order_id="E")
    store.send("E", "cell1", expires=time.time() + 30)
    assert store.take_report("cell1", report(1, "order-accepted", "E")).text
    # A seq far ahead is refused, not trusted; the factory asks for what follows seq 1.
    ahead = store.take_report("cell1", report(99998, "step-started", "E"))
    assert ahead.ask_after == 1 and ahead.refused and "the next one is 2" in ahead.refused
    assert store.cells()["cell1"].seq == 1 and store.get("E").state == "accepted"
    assert store.take_report("cell1", report(2, "step-started", "E")).ask_after is None
    assert store.get("E").state == "in-progress"
    assert store.take_report("cell1", report(2, "step-started", "E")) == ((None, None, None))
    # A new mailbox (its epoch new): followed from its seq 1; one from its middle is refused
    # and the factory asks for its reports from the start.
    other = "fedcba9876543210"
    middle = store.take_report("cell1", report(5, "order-done", "E", epoch=other))
    assert middle.ask_after == 0 and store.get("E").state == "in-progress"
    assert store.cells()["cell1"].epoch == other and store.cells()["cell1"].seq == 0
    for seq in range(1, 5):
        assert store.take_report("cell1", report(seq, "step-finished", "E", epoch=other))[1:] == (
            None,
            None,
        )
    store.take_report("cell1", report(5, "order-done", "E", epoch=other))
    assert store.get("E").state == "done" and store.cells()["cell1"].seq == 5
    # A withdrawn acceptance keeps the numbering and changes nothing.
    store.submit("wax-robot-base", 1, order_id="W")
    store.send("W", "cell1", expires=time.time() + 30)
    store.take_report("cell1", report(6, "order-accepted", "W", epoch=other, withdrawn=True))
    assert store.get("W").state == "sent" and store.cells()["cell1"].seq == 6


def test_an_order_is_never_seen_sent_without_why(store: FactoryStore) -> None:
    """The reason for a choice of cell is logged in the commit that marks the order sent."""
    store.submit("wax-robot-base", 2, order_id="W1")
    (sent,) = store.send_many([("W1", "cell1")], time.time() + 60, {"W1": "cell1 is idle"})
    assert sent.state == "sent" and sent.cell == "cell1"
    texts = [e.text for e in store.events() if e.order_id == "W1"]
    assert texts[-2:] == ["order W1: cell1 is idle", "order W1 sent to cell1"]  # why first


def test_parts_made_and_held_follow_the_cells_reports(store: FactoryStore) -> None:
    """Done counts each part the cell says is made, as it comes; held is the parts held now
    by id: a waiting part scrapped was never held, and the order is held while one is."""
    store.submit("wax-robot-base", 4, order_id="K")
    store.send("K", "cell1", expires=time.time() + 30)
    made = {"part_done": True}
    steps = [
        (report(1, "order-accepted", "K"), ("accepted", 0, (), 0)),
        (report(2, "step-started", "K", part_id="K-1"), ("in-progress", 0, (), 0)),
        (report(3, "step-finished", "K", part_id="K-1"), ("in-progress", 0, (), 0)),
        (report(4, "step-finished", "K", part_id="K-1", data=made), ("in-progress", 1, (), 0)),
        (report(5, "part-held", "K", part_id="K-2"), ("held", 1, ("K-2",), 0)),
        (report(6, "step-started", "K", part_id="K-3"), ("held", 1, ("K-2",), 0)),
        (report(7, "part-scrapped", "K", part_id="K-4"), ("held", 1, ("K-2",), 1)),
        (report(8, "step-finished", "K", part_id="K-3", data=made), ("held", 2, ("K-2",), 1)),
        (report(9, "part-scrapped", "K", part_id="K-2"), ("in-progress", 2, (), 2)),
        (report(10, "order-done", "K"), ("done", 2, (), 2)),
    ]
    for r, expected in steps:
        store.take_report("cell1", r)
        k = store.get("K")
        assert (k.state, k.done, k.held_parts, k.scrapped) == expected, r
        assert k.held == len(k.held_parts)
    # A part released on the outfeed (its route machined) is made; one released elsewhere
    # goes on, and the order with it.
    store.submit("wax-robot-base", 2, order_id="R")
    store.send("R", "cell1", expires=time.time() + 30)
    for seq, kind, part, data in [
        (11, "order-accepted", None, {}),
        (12, "part-held", "R-1", {}),
        (13, "part-held", "R-2", {}),
        (14, "part-released", "R-1", {"redo": False, "location": "out", "part_done": True}),
        (15, "part-released", "R-2", {"redo": True, "location": "cnc1", "part_done": False}),
    ]:
        store.take_report("cell1", report(seq, kind, "R", part_id=part, data=data))
    r = store.get("R")
    assert (r.state, r.done, r.held) == ("in-progress", 1, 0)
