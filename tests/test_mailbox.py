"""The SQLite mailbox: idempotent posts, ordering, transitions, two processes at once."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellctl.clock import RealClock
from cellctl.errors import UsageError
from cellctl.mailbox import (
    REPORT_KINDS,
    Mailbox,
    SqliteMailbox,
    open_mailbox,
)


class FakeClock(RealClock):
    """Times the test chooses, so "oldest first" does not depend on the wall clock."""

    def __init__(self) -> None:
        super().__init__()
        self.at = 1000.0

    def now(self) -> float:
        self.at += 1.0
        return self.at


@pytest.fixture
def mailbox(tmp_path: Path) -> Iterator[Mailbox]:
    with SqliteMailbox(tmp_path / "mailbox.sqlite3", clock=FakeClock()) as mb:
        yield mb


def test_post_order_is_idempotent_per_id(mailbox: Mailbox) -> None:
    first, new = mailbox.post_order("wax-robot", qty=3, priority=2, order_id="A17")
    assert new
    assert (first.id, first.part_type, first.qty, first.priority) == ("A17", "wax-robot", 3, 2)
    assert first.state == "posted"

    again, new_again = mailbox.post_order("other", qty=9, priority=9, order_id="A17")
    assert not new_again
    assert again == first
    assert mailbox.orders() == [first]


def test_generated_ids_are_distinct(mailbox: Mailbox) -> None:
    a, _ = mailbox.post_order("p")
    b, _ = mailbox.post_order("p")
    assert a.id != b.id
    assert {o.id for o in mailbox.orders()} == {a.id, b.id}


@pytest.mark.parametrize(
    ("part_type", "qty", "order_id"),
    [("", 1, None), ("p", 0, None), ("p", 1, "two words"), ("p", 1, "")],
)
def test_bad_orders_are_refused(
    mailbox: Mailbox, part_type: str, qty: int, order_id: str | None
) -> None:
    with pytest.raises(UsageError):
        mailbox.post_order(part_type, qty=qty, order_id=order_id)
    assert mailbox.orders() == []


@pytest.mark.parametrize("order_id", ["A\x1b[2J", "B\x1b]0;title\x07", "C\x00", "D\u202e"])
def test_an_order_id_with_control_characters_is_refused(mailbox: Mailbox, order_id: str) -> None:
    # Listed by `cellctl orders`, an escape sequence would act on the operator's terminal.
    with pytest.raises(UsageError, match="must be printable text"):
        mailbox.post_order("p", qty=1, order_id=order_id)
    assert mailbox.orders() == []
    assert mailbox.post_order("p", qty=1, order_id="Ä-1/x")[0].id == "Ä-1/x"


def test_orders_highest_priority_first_then_oldest(mailbox: Mailbox) -> None:
    for oid, prio in [("low-old", 0), ("high-old", 5), ("low-new", 0), ("high-new", 5)]:
        mailbox.post_order("p", priority=prio, order_id=oid)
    assert [o.id for o in mailbox.orders()] == ["high-old", "high-new", "low-old", "low-new"]


def test_pending_orders_and_state_filter(mailbox: Mailbox) -> None:
    for oid in ["a", "b", "c"]:
        mailbox.post_order("p", order_id=oid)
    mailbox.set_order_state("b", "accepted")
    assert [o.id for o in mailbox.pending_orders()] == ["a", "c"]
    assert [o.id for o in mailbox.orders(["accepted"])] == ["b"]
    assert mailbox.orders([]) == []


def test_order_lifecycle(mailbox: Mailbox) -> None:
    mailbox.post_order("p", order_id="o1")
    for state in ["accepted", "in-progress", "held", "in-progress", "done"]:
        order = mailbox.set_order_state("o1", state, note=f"now {state}")
        assert order.state == state
        assert mailbox.get_order("o1") == order
    assert mailbox.get_order("o1").note == "now done"


def test_a_note_belongs_to_its_state(mailbox: Mailbox) -> None:
    mailbox.post_order("p", order_id="o1")
    mailbox.set_order_state("o1", "accepted")
    mailbox.set_order_state("o1", "held", "a part needs the operator")
    # The same state again (a controller after a restart): the note stays.
    assert mailbox.set_order_state("o1", "held").note == "a part needs the operator"
    # A new state without a note: no note (the held order's is not the running order's).
    assert mailbox.set_order_state("o1", "in-progress").note == ""
    assert mailbox.get_order("o1").note == ""


@pytest.mark.parametrize(
    ("path", "illegal"),
    [
        ([], "in-progress"),
        ([], "done"),
        (["accepted"], "posted"),
        (["accepted", "done"], "in-progress"),
        (["cancelled"], "accepted"),
        (["failed"], "held"),
        ([], "exploded"),
    ],
)
def test_illegal_transitions_are_refused(mailbox: Mailbox, path: list[str], illegal: str) -> None:
    mailbox.post_order("p", order_id="o1")
    for state in path:
        mailbox.set_order_state("o1", state)
    before = mailbox.get_order("o1")
    with pytest.raises(UsageError, match=r"o1|unknown"):
        mailbox.set_order_state("o1", illegal)
    assert mailbox.get_order("o1") == before


def test_setting_the_same_state_again_changes_nothing(mailbox: Mailbox) -> None:
    mailbox.post_order("p", order_id="o1")
    accepted = mailbox.set_order_state("o1", "accepted")
    assert mailbox.set_order_state("o1", "accepted") == accepted


def test_unknown_order(mailbox: Mailbox) -> None:
    with pytest.raises(UsageError, match="no order 'nope'"):
        mailbox.get_order("nope")
    with pytest.raises(UsageError, match="no order 'nope'"):
        mailbox.set_order_state("nope", "accepted")


def test_reports_in_sequence(mailbox: Mailbox) -> None:
    r1 = mailbox.post_report("order-accepted", "accepted", order_id="o1")
    r2 = mailbox.post_report(
        "step-started", "cnc1 roughing", order_id="o1", part_id="o1-1", data={"machine": "cnc1"}
    )
    r3 = mailbox.post_report("alarm-raised", "cnc1 door open", data={"alarm": 4})
    assert [r.seq for r in (r1, r2, r3)] == [1, 2, 3]
    assert mailbox.reports() == [r1, r2, r3]
    assert mailbox.reports(since_seq=1) == [r2, r3]
    assert mailbox.reports(since_seq=1, limit=1) == [r2]
    assert mailbox.reports()[1].data == {"machine": "cnc1"}
    assert mailbox.reports()[1].part_id == "o1-1"


def test_report_kind_and_data_are_checked(mailbox: Mailbox) -> None:
    assert "order-done" in REPORT_KINDS
    with pytest.raises(UsageError, match="unknown report kind"):
        mailbox.post_report("coffee-ready", "x")
    with pytest.raises(UsageError, match="JSON"):
        mailbox.post_report("order-done", "x", data={"when": object()})
    assert mailbox.reports() == []


def test_open_mailbox_default_and_unknown_backend(tmp_path: Path) -> None:
    with open_mailbox(tmp_path / "cell") as mb:
        mb.post_order("p", order_id="x")
    assert (tmp_path / "cell" / "mailbox.sqlite3").exists()
    with open_mailbox(
        tmp_path / "elsewhere", f"sqlite://{tmp_path / 'cell' / 'mailbox.sqlite3'}"
    ) as mb:
        assert [o.id for o in mb.orders()] == ["x"]
    with pytest.raises(UsageError, match="no such mailbox backend"):
        open_mailbox(tmp_path, "mqtt://broker:1883/cell1")


def test_data_survives_reopening(tmp_path: Path) -> None:
    with open_mailbox(tmp_path) as mb:
        mb.post_order("p", order_id="keep")
        mb.post_order("p", order_id="due", due=1_800_000_000.5)
        mb.post_report("order-accepted", "ok", order_id="keep")
    with open_mailbox(tmp_path) as mb:
        assert mb.get_order("keep").part_type == "p"
        assert mb.due_times() == {"due": 1_800_000_000.5}
        assert [r.kind for r in mb.reports()] == ["order-accepted"]


WRITER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from cellctl.mailbox import open_mailbox

    name, cell, count = sys.argv[1], Path(sys.argv[2]), int(sys.argv[3])
    mb = open_mailbox(cell)
    print("ready", flush=True)
    sys.stdin.readline()  # start together with the other writer
    created = 0
    for i in range(count):
        _, new = mb.post_order("p", order_id=f"shared-{i}")
        created += new
        mb.post_order("p", order_id=f"{name}-{i}")
        mb.post_report("step-started", f"{name} {i}", data={"writer": name, "i": i})
        order = mb.get_order(f"{name}-{i}")
        mb.set_order_state(order.id, "accepted")
    mb.close()
    print(created, flush=True)
    """
)


def test_two_processes_writing_at_once_lose_nothing(tmp_path: Path) -> None:
    count = 150
    open_mailbox(tmp_path).close()
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", WRITER, name, str(tmp_path), str(count)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for name in ("w1", "w2")
    ]
    for p in procs:
        assert p.stdout is not None
        assert p.stdout.readline().strip() == "ready"
    for p in procs:
        assert p.stdin is not None
        p.stdin.write("go\n")
        p.stdin.flush()
    results = [p.communicate(timeout=100) for p in procs]
    for p, (_, err) in zip(procs, results, strict=True):
        assert p.returncode == 0, err
        assert "locked" not in err
    created = [int(out.strip()) for out, _ in results]
    # Each shared id was created exactly once, by one writer or the other.
    assert sum(created) == count

    with open_mailbox(tmp_path) as mb:
        orders = mb.orders()
        assert len(orders) == 3 * count
        assert len(mb.orders(["accepted"])) == 2 * count
        reports = mb.reports()
        assert [r.seq for r in reports] == list(range(1, 2 * count + 1))
        per_writer = Counter(r.data["writer"] for r in reports)
        assert per_writer == {"w1": count, "w2": count}
