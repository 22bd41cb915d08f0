"""The journal: parts, steps, recovery after SIGKILL, operator release/scrap, alarms, figures."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from cellctl.cell.journal import Journal, open_journal
from cellctl.clock import RealClock
from cellctl.errors import UsageError
from tests.conftest import released_together


@dataclass(frozen=True)
class AnOrder:
    id: str
    part_type: str
    qty: int


class Clock(RealClock):
    """A clock the test sets, so figures are exact and need no waiting."""

    def __init__(self) -> None:
        super().__init__()
        self.at = 100.0  # the wall time the test sets

    def now(self) -> float:
        return self.at


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def journal(tmp_path: Path, clock: Clock) -> Iterator[Journal]:
    with open_journal(tmp_path, clock=clock) as j:
        yield j


def test_create_parts_is_idempotent_per_order(journal: Journal) -> None:
    parts = journal.create_parts(AnOrder("A17", "wax-robot", 3))
    assert [p.id for p in parts] == ["A17-1", "A17-2", "A17-3"]
    assert {(p.location, p.status, p.route_index) for p in parts} == {("conveyor", "waiting", 0)}
    assert [p.seq_in_order for p in parts] == [1, 2, 3]
    assert journal.create_parts(AnOrder("A17", "wax-robot", 3)) == parts
    assert journal.parts() == parts


def test_parts_filters(journal: Journal) -> None:
    journal.create_parts(AnOrder("a", "p", 2))
    journal.create_parts(AnOrder("b", "p", 1))
    journal.hold_part("a-2", "looks wrong")
    assert [p.id for p in journal.parts(order_id="a")] == ["a-1", "a-2"]
    assert [p.id for p in journal.parts(["held"])] == ["a-2"]
    assert [p.id for p in journal.parts(["waiting"], order_id="b")] == ["b-1"]
    assert journal.get_part("a-2").note == "looks wrong"
    with pytest.raises(UsageError, match="no part 'zz'"):
        journal.get_part("zz")


def test_a_step_makes_the_part_active_then_moves_it(journal: Journal) -> None:
    journal.create_parts(AnOrder("o", "p", 1))
    step = journal.begin_step("o-1", "transfer", "robot", "conveyor-to-cnc1")
    assert (step.state, step.attempt, step.route_index) == ("started", 1, 0)
    assert journal.get_part("o-1").status == "active"
    assert journal.open_steps() == [step]
    with pytest.raises(UsageError, match="active"):
        journal.begin_step("o-1", "machine", "cnc1", "ROUGH")

    ended = journal.end_step(step.id, "finished", "placed", location="cnc1")
    assert (ended.state, ended.outcome) == ("finished", "placed")
    assert ended.ended is not None
    part = journal.get_part("o-1")
    assert (part.status, part.location, part.route_index) == ("waiting", "cnc1", 0)
    assert journal.open_steps() == []
    # Ending it again the same way is harmless; another way is refused.
    assert journal.end_step(step.id, "finished") == ended
    with pytest.raises(UsageError, match="already finished"):
        journal.end_step(step.id, "failed")

    cut = journal.begin_step("o-1", "machine", "cnc1", "ROUGH")
    assert not journal.step_done("o-1", "machine", "cnc1", "ROUGH", 0)
    journal.end_step(cut.id, "finished", route_index=1)
    assert journal.step_done("o-1", "machine", "cnc1", "ROUGH", 0)
    assert journal.get_part("o-1").route_index == 1
    assert [s.id for s in journal.steps("o-1")] == [step.id, cut.id]


def test_failed_step_can_hold_its_part_in_the_same_write(journal: Journal) -> None:
    journal.create_parts(AnOrder("o", "p", 1))
    step = journal.begin_step("o-1", "machine", "cnc2", "FINISH")
    journal.end_step(step.id, "failed", "spindle stalled", hold="spindle stalled mid-cut")
    part = journal.get_part("o-1")
    assert (part.status, part.note) == ("held", "spindle stalled mid-cut")
    assert not journal.step_done("o-1", "machine", "cnc2", "FINISH", 0)
    journal.release_part("o-1", redo_step=True)
    again = journal.begin_step("o-1", "machine", "cnc2", "FINISH")
    assert again.attempt == 2


def test_bad_arguments_are_refused(journal: Journal) -> None:
    journal.create_parts(AnOrder("o", "p", 1))
    with pytest.raises(UsageError, match="unknown step kind"):
        journal.begin_step("o-1", "polish", "cnc1", "X")
    with pytest.raises(UsageError, match="one word"):
        journal.move_part("o-1", "the floor")
    with pytest.raises(UsageError, match="no part"):
        journal.begin_step("nope", "machine", "cnc1", "X")
    step = journal.begin_step("o-1", "machine", "cnc1", "X")
    with pytest.raises(UsageError, match="finished or failed"):
        journal.end_step(step.id, "interrupted")
    with pytest.raises(UsageError, match="no step"):
        journal.end_step(999, "finished")
    with pytest.raises(UsageError, match="in flight"):
        journal.hold_part("o-1", "why not")
    with pytest.raises(UsageError, match="active"):
        journal.scrap_part("o-1", "why not")
    with pytest.raises(UsageError, match="active"):
        journal.finish_part("o-1")
    assert journal.get_part("o-1").status == "active"


def test_recover_holds_interrupted_parts_and_repeats_nothing(journal: Journal) -> None:
    journal.create_parts(AnOrder("o", "p", 3))
    done = journal.begin_step("o-1", "machine", "cnc1", "ROUGH")
    journal.end_step(done.id, "finished", route_index=1)
    cutting = journal.begin_step("o-2", "machine", "cnc1", "ROUGH")
    carrying = journal.begin_step("o-3", "transfer", "robot", "conveyor-to-cnc2")

    report = journal.recover()
    assert [s.id for s in report.interrupted] == [cutting.id, carrying.id]
    assert {s.state for s in report.interrupted} == {"interrupted"}
    held = {p.id: p for p in report.held}
    assert set(held) == {"o-2", "o-3"}
    assert held["o-2"].note.startswith("needs inspection")
    assert "ROUGH" in held["o-2"].note
    assert held["o-3"].note == "interrupted transfer: check the gripper and both stations"
    assert journal.get_part("o-1").status == "waiting"
    assert journal.open_steps() == []
    assert journal.recover().clean

    # A held part is never started again until the operator says so.
    with pytest.raises(UsageError, match="held"):
        journal.begin_step("o-2", "machine", "cnc1", "ROUGH")


def test_release_without_redo_counts_the_interrupted_step_as_done(journal: Journal) -> None:
    journal.create_parts(AnOrder("o", "p", 1))
    journal.move_part("o-1", "cnc1")
    journal.begin_step("o-1", "machine", "cnc1", "ROUGH")
    journal.recover()

    part = journal.release_part("o-1")
    assert (part.status, part.location, part.route_index, part.note) == (
        "waiting",
        "cnc1",
        0,
        "",
    )
    assert journal.step_done("o-1", "machine", "cnc1", "ROUGH", 0)
    assert journal.steps("o-1")[0].resolution == "accepted"


def test_release_with_redo_runs_the_step_again(journal: Journal) -> None:
    journal.create_parts(AnOrder("o", "p", 1))
    journal.begin_step("o-1", "machine", "cnc1", "ROUGH")
    journal.recover()
    journal.release_part("o-1", redo_step=True)
    assert not journal.step_done("o-1", "machine", "cnc1", "ROUGH", 0)
    assert journal.begin_step("o-1", "machine", "cnc1", "ROUGH").attempt == 2


def test_release_after_interrupted_transfer_needs_the_location(journal: Journal) -> None:
    journal.create_parts(AnOrder("o", "p", 1))
    journal.begin_step("o-1", "transfer", "robot", "conveyor-to-cnc1")
    journal.recover()
    with pytest.raises(UsageError, match="say where it is now"):
        journal.release_part("o-1")
    assert journal.get_part("o-1").status == "held"
    part = journal.release_part("o-1", location="cnc1")
    assert (part.status, part.location) == ("waiting", "cnc1")


def test_scrap_and_finish(journal: Journal) -> None:
    journal.create_parts(AnOrder("o", "p", 2))
    journal.begin_step("o-1", "machine", "cnc1", "ROUGH")
    journal.recover()
    scrapped = journal.scrap_part("o-1", "gouged")
    assert (scrapped.status, scrapped.note) == ("scrapped", "gouged")
    assert journal.scrap_part("o-1", "again") == scrapped
    with pytest.raises(UsageError, match="scrapped"):
        journal.release_part("o-1")
    with pytest.raises(UsageError, match="scrapped"):
        journal.begin_step("o-1", "machine", "cnc1", "ROUGH")

    journal.move_part("o-2", "out", route_index=4)
    finished = journal.finish_part("o-2")
    assert (finished.status, finished.location, finished.route_index) == ("done", "out", 4)
    assert journal.finish_part("o-2") == finished
    with pytest.raises(UsageError, match="done"):
        journal.scrap_part("o-2", "late")


def test_hold_by_hand_and_release(journal: Journal) -> None:
    journal.create_parts(AnOrder("o", "p", 1))
    held = journal.hold_part("o-1", "operator wants a look")
    assert journal.hold_part("o-1", "again") == held
    with pytest.raises(UsageError, match="no step to redo"):
        journal.release_part("o-1", redo_step=True)
    assert journal.release_part("o-1").status == "waiting"
    with pytest.raises(UsageError, match="waiting"):
        journal.release_part("o-1")


def test_alarms_are_not_duplicated_and_clear_once(journal: Journal, clock: Clock) -> None:
    a, new = journal.raise_alarm("cnc1", "64", "door open")
    assert new and a.state == "active"
    same, new_again = journal.raise_alarm("cnc1", "64", "door open")
    assert (same, new_again) == (a, False)
    b, _ = journal.raise_alarm("cnc2", "64", "door open")
    assert [x.id for x in journal.active_alarms()] == [a.id, b.id]

    clock.at = 200.0
    cleared = journal.clear_alarm(a.id)
    assert (cleared.state, cleared.cleared, cleared.cleared_by) == ("cleared", 200.0, "operator")
    assert journal.clear_alarm(a.id, by="controller") == cleared
    assert [x.id for x in journal.active_alarms()] == [b.id]
    # The same fault after a clear is a new alarm.
    c, new_c = journal.raise_alarm("cnc1", "64", "door open")
    assert new_c and c.id not in (a.id, b.id)
    assert [x.id for x in journal.alarms()] == [a.id, b.id, c.id]
    with pytest.raises(UsageError, match="no alarm 99"):
        journal.clear_alarm(99)


def test_machine_service(journal: Journal) -> None:
    assert journal.machines_out_of_service() == {}
    journal.set_machine_service("cnc2", False, "cutter broken")
    journal.set_machine_service("cnc1", True)
    assert journal.machines_out_of_service() == {"cnc2": "cutter broken"}
    journal.set_machine_service("cnc2", True, "new cutter")
    assert journal.machines_out_of_service() == {}


def test_busy_time_and_makespan(journal: Journal, clock: Clock) -> None:
    journal.create_parts(AnOrder("o", "p", 2))
    journal.create_parts(AnOrder("q", "p", 1))
    for part, start, end in [("o-1", 100.0, 130.0), ("o-2", 140.0, 150.0)]:
        clock.at = start
        step = journal.begin_step(part, "machine", "cnc1", "ROUGH")
        clock.at = end
        journal.end_step(step.id, "finished")
    clock.at = 160.0
    open_step = journal.begin_step("q-1", "machine", "cnc2", "FINISH")

    assert journal.busy_time("cnc1") == 40.0
    assert journal.busy_time("cnc1", since=120.0) == 20.0
    assert journal.busy_time("cnc1", since=120.0, until=145.0) == 15.0
    assert journal.busy_time("cnc2", until=170.0) == 10.0
    assert journal.busy_time("robot") == 0.0
    assert journal.makespan("o") == 50.0
    assert journal.makespan("q") is None
    clock.at = 190.0
    journal.end_step(open_step.id, "finished")
    assert journal.makespan() == 90.0


def test_journal_survives_reopening(tmp_path: Path) -> None:
    with open_journal(tmp_path) as j:
        j.create_parts(AnOrder("o", "p", 1))
        j.begin_step("o-1", "machine", "cnc1", "ROUGH")
    with open_journal(tmp_path) as j:
        assert [s.program for s in j.open_steps()] == ["ROUGH"]
        assert (tmp_path / "journal.sqlite3").exists()


# -- a controller killed with SIGKILL ----------------------------------------------------------

# Runs parts through transfer -> machine steps and prints each journal write after it
# returned; with STOP_AT it blocks (on stdin) right after beginning that many steps.
WORKER = textwrap.dedent(
    """
    import sys
    from dataclasses import dataclass
    from pathlib import Path
    from cellctl.cell.journal import open_journal

    @dataclass
    class O:
        id: str
        part_type: str
        qty: int

    cell, stop_at = Path(sys.argv[1]), int(sys.argv[2])
    j = open_journal(cell)
    parts = j.create_parts(O("k", "p", 1000))
    begun = 0
    for part in parts:
        for kind, machine, program, loc in [
            ("transfer", "robot", "conveyor-to-cnc1", "cnc1"),
            ("machine", "cnc1", "ROUGH", None),
        ]:
            step = j.begin_step(part.id, kind, machine, program)
            begun += 1
            print("begun", step.id, kind, part.id, flush=True)
            if begun == stop_at:
                sys.stdin.readline()
            j.end_step(step.id, "finished", location=loc)
            print("ended", step.id, flush=True)
    """
)


def start_worker(cell: Path, stop_at: int) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", WORKER, str(cell), str(stop_at)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def kill(proc: subprocess.Popen[str]) -> None:
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    for stream in (proc.stdin, proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()


@pytest.mark.parametrize(("stop_at", "kind"), [(6, "machine"), (7, "transfer")])
def test_sigkill_mid_step_leaves_exactly_that_step_open(
    tmp_path: Path, stop_at: int, kind: str
) -> None:
    proc = start_worker(tmp_path, stop_at)
    assert proc.stdout is not None
    lines = []
    while len(lines) < 2 * stop_at - 1:
        line = proc.stdout.readline()
        assert line, proc.stderr.read() if proc.stderr else ""
        lines.append(line.split())
    last = lines[-1]
    assert last[0] == "begun" and last[2] == kind
    kill(proc)

    with open_journal(tmp_path) as j:
        report = j.recover()
        assert [s.id for s in report.interrupted] == [int(last[1])]
        assert [p.id for p in report.held] == [last[3]]
        if kind == "machine":
            assert report.held[0].note.startswith("needs inspection")
        else:
            assert report.held[0].note.startswith("interrupted transfer")
        finished = [s for s in j.steps() if s.state == "finished"]
        assert len(finished) == stop_at - 1
        # Finished steps are known as done, so a restarted controller skips them.
        assert j.step_done("k-1", "machine", "cnc1", "ROUGH", 0)
        assert j.get_part("k-1").location == "cnc1"


def test_sigkill_at_any_instant_loses_no_returned_write(tmp_path: Path) -> None:
    proc = start_worker(tmp_path, stop_at=0)
    assert proc.stdout is not None
    seen: list[list[str]] = []
    while len(seen) < 301:
        line = proc.stdout.readline()
        assert line
        seen.append(line.split())
    kill(proc)

    begun = {int(w[1]) for w in seen if w[0] == "begun"}
    ended = {int(w[1]) for w in seen if w[0] == "ended"}
    with open_journal(tmp_path) as j:
        open_before = j.open_steps()
        assert len(open_before) <= 1
        steps = {s.id: s for s in j.steps()}
        # Every write the worker saw return is in the journal.
        assert begun <= set(steps)
        assert all(steps[i].state == "finished" for i in ended)
        report = j.recover()
        assert [s.id for s in report.interrupted] == [s.id for s in open_before]
        assert len(report.held) == len(open_before)
        assert j.open_steps() == []
        assert len(j.parts(["active"])) == 0


# -- two processes at once ---------------------------------------------------------------------

OPERATOR = textwrap.dedent(
    """
    import sys
    from dataclasses import dataclass
    from pathlib import Path
    from cellctl.cell.journal import open_journal

    @dataclass
    class O:
        id: str
        part_type: str
        qty: int

    name, cell = sys.argv[1], Path(sys.argv[2])
    j = open_journal(cell)
    print("ready", flush=True)
    sys.stdin.readline()
    for i in range(100):
        j.create_parts(O("shared", "p", 5))
        alarm, _ = j.raise_alarm("cnc1", str(i), f"{name} {i}")
        j.clear_alarm(alarm.id, by=name)
        j.create_parts(O(f"{name}-{i}", "p", 1))
        step = j.begin_step(f"{name}-{i}-1", "machine", "cnc1", "ROUGH")
        j.end_step(step.id, "finished")
    print("done", flush=True)
    """
)


def test_two_processes_writing_at_once_lose_nothing(tmp_path: Path) -> None:
    open_journal(tmp_path).close()
    argvs = [["a", str(tmp_path)], ["b", str(tmp_path)]]
    for code, out, err in released_together(OPERATOR, argvs, timeout=100):
        assert code == 0, err
        assert out.strip() == "done"

    with open_journal(tmp_path) as j:
        assert len(j.parts(order_id="shared")) == 5
        assert len(j.parts()) == 205
        assert len(j.alarms()) == 200
        assert j.active_alarms() == []
        assert {a.cleared_by for a in j.alarms()} == {"a", "b"}
        assert len([s for s in j.steps() if s.state == "finished"]) == 200


def _other_process(directory: Path, code: str) -> str:
    """Run ``code`` (with ``j``, the journal of ``directory``, open) in a new process."""
    script = textwrap.dedent(
        """
        import sys
        from pathlib import Path
        from cellctl.cell.journal import open_journal
        with open_journal(Path(sys.argv[1])) as j:
            print({code})
        """
    ).format(code=code)
    done = subprocess.run(
        [sys.executable, "-c", script, str(directory)], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_a_second_store_in_the_process_keeps_the_first_ones_writes_visible(
    tmp_path: Path,
) -> None:
    """The controller's journal, then a second store on the same file in the same process
    (the API's audit trail), then a command in another process that opens the journal and
    closes it: what the controller writes afterwards is still seen by everyone else. (Opening
    the file by hand beside a live connection dropped its locks; the other process, seeing no
    reader, deleted the -wal at its close, and later writes went into the deleted file.)"""
    with open_journal(tmp_path) as journal:
        journal.raise_alarm("robot", "link", "before")
        with open_journal(tmp_path) as second:
            second.raise_alarm("cnc1", "link", "beside")
        assert _other_process(tmp_path, "len(j.alarms())") == "2"
        journal.raise_alarm("cnc2", "link", "after")
        texts = _other_process(tmp_path, "sorted(a.text for a in j.alarms())")
        assert texts == str(["after", "before", "beside"])
        assert (tmp_path / "journal.sqlite3-wal").exists()


def test_the_places_a_part_was_taken_out_of_are_kept_until_their_vise_is_open(
    tmp_path: Path, clock: Clock
) -> None:
    """Kept in the file with the scrap, in one transaction: another connection (the CLI, a
    restarted controller) sees them, until one says the vise is open."""
    with open_journal(tmp_path, clock=clock) as j, open_journal(tmp_path, clock=clock) as other:
        first, second = j.create_parts(AnOrder("A", "wax-robot", 2))
        assert other.emptied_places() == {}
        j.scrap_part(first.id, "cut short", taken_out_of=["cnc2"])
        j.scrap_part(second.id, "dropped")
        assert other.emptied_places() == {"cnc2": first.id}
        other.vise_open("cnc2")
        assert j.emptied_places() == {}
    with open_journal(tmp_path, clock=clock) as again:
        assert again.emptied_places() == {}
        assert [p.status for p in again.parts(order_id="A")] == ["scrapped", "scrapped"]
