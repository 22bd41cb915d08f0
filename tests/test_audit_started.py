"""An acting call is in the audit trail from the moment it begins: at the time it began, first
``running``, then its end on the same entry. A ``cellctl run`` killed (kill -9) in the middle
of a long call leaves it on record; the next controller marks it interrupted, while a
command reading the trail beside a running controller leaves its calls alone. An older
journal's trail still opens and lists. Real ``cellctl`` processes, real signals, the
emulated cell."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from cellctl.cell.journal import JOURNAL_FILE, open_journal
from cellctl.service.audit import INTERRUPTED, RUNNING, AuditEntry, AuditLog, mark_interrupted
from cellctl.ui.cli import main as cli_main
from tests.conftest import CELLCTL, emulated_cell_process, wait_until
from tests.test_api_hardening import Stalled, answer, call, stalled  # noqa: F401  (the fixture)

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell"
#: Machine time 20 times real: cnc2's finishing program takes tens of seconds to cut, and
#: its download call lasts as long (it ends with the cut).
TIME_SCALE = "20"
PROGRAM = "toy_mill_table_finish_cnc2.dyn"
#: How long a command may take to come up on a busy box (a Python start, a cell's machines).
STARTED_S = 90.0
#: A hang guard, not a timing figure.
GUARD_S = 60.0


def cellctl(cell: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "--cell", str(cell), *args], capture_output=True, text=True, timeout=GUARD_S
    )


def downloads(cell: Path) -> list[AuditEntry]:
    """The trail's mill.download entries, read as any reader does (no controller's right)."""
    with AuditLog(cell) as log:
        return [e for e in log.entries() if e.method == "mill.download"]


def listed(cell: Path) -> list[dict[str, Any]]:
    """``cellctl audit --json --since 5m``: what the user reads."""
    done = cellctl(cell, "audit", "--json", "--since", "5m")
    assert done.returncode == 0, done.stderr
    found: list[dict[str, Any]] = json.loads(done.stdout)
    return found


@contextmanager
def processes() -> Iterator[list[subprocess.Popen[str]]]:
    """Every process a test starts ends with it (killed if it is still running)."""
    started: list[subprocess.Popen[str]] = []
    try:
        yield started
    finally:
        for proc in started:
            if proc.poll() is None:
                proc.kill()
            proc.wait(GUARD_S)


def start(procs: list[subprocess.Popen[str]], cell: Path, out: Path, *args: str) -> Any:
    with out.open("w") as sink:
        proc = subprocess.Popen(
            [*CELLCTL, "--cell", str(cell), *args],
            stdin=subprocess.DEVNULL,
            stdout=sink,
            stderr=subprocess.STDOUT,
            text=True,
        )
    procs.append(proc)
    return proc


@pytest.mark.timeout(400)  # two controllers starting on a busy box: waiting, not CPU
def test_a_call_cut_by_kill_9_is_on_record_as_begun_and_marked_interrupted(
    tmp_path: Path,
) -> None:
    with ExitStack() as stack:
        cell = stack.enter_context(emulated_cell_process(tmp_path / "cell", TIME_SCALE))
        procs = stack.enter_context(processes())
        run_log, second_log = tmp_path / "run.log", tmp_path / "run2.log"
        run = start(procs, cell, run_log, "run", "--no-live")
        wait_until(lambda: "connected to" in run_log.read_text(), "the controller", STARTED_S)
        out = cellctl(cell, "machine", "cnc2", "out", "--reason", "a program by hand")
        assert out.returncode == 0, out.stderr
        wait_until(
            lambda: "state 2" in cellctl(cell, "mill", "cnc2", "status").stdout,
            "cnc2 ready for a program by hand",
            STARTED_S,
        )
        program = str(cell / "programs" / PROGRAM)
        download = start(
            procs, cell, tmp_path / "download.log", "mill", "cnc2", "download", program
        )
        wait_until(
            lambda: [e for e in downloads(cell) if e.result == RUNNING], "the call on record"
        )
        [began] = downloads(cell)
        # Listed as it runs, through the controller; the command that listed it (another
        # process, not the cell's owner) left it running.
        [shown] = [e for e in listed(cell) if e["method"] == "mill.download"]
        assert (shown["at"], shown["result"], shown["ended"]) == (began.at, RUNNING, None)
        assert f'"program":"{PROGRAM}"' in shown["params"]  # (its text cut to 500 characters)

        os.kill(run.pid, signal.SIGKILL)  # a power cut, as far as the cell can tell
        run.wait(GUARD_S)
        assert download.wait(GUARD_S) != 0  # its client saw the API go, not an answer
        [after_kill] = downloads(cell)
        assert after_kill.result == RUNNING, "the download ended before the kill: too short"
        # A command with no controller running reads the trail in its own process: it
        # leaves the entry alone too (only the cell's next controller may say it was cut).
        assert [e["result"] for e in listed(cell) if e["method"] == "mill.download"] == [RUNNING]

        second = start(procs, cell, second_log, "run", "--no-live")
        wait_until(lambda: "control API on" in second_log.read_text(), "the restart", STARTED_S)
        [cut] = downloads(cell)
        assert (cut.id, cut.at, cut.who) == (began.id, began.at, "token:default")
        assert cut.result == INTERRUPTED and cut.result.startswith("interrupted: ")
        assert cut.ended is None  # when it ended is not known
        said = " ".join(second_log.read_text().split())
        assert "audit: mill.download by token:default, begun" in said
        assert "marked interrupted" in said
        # What the user reads after the restart: the act, when it began, cut short.
        [shown] = [e for e in listed(cell) if e["method"] == "mill.download"]
        assert (shown["at"], shown["result"]) == (began.at, INTERRUPTED)
        table = cellctl(cell, "audit", "--since", "5m")
        assert table.returncode == 0 and "interrupted" in table.stdout, table.stdout
        second.send_signal(signal.SIGINT)
        assert second.wait(GUARD_S) == 0, second_log.read_text()


async def test_a_long_call_is_listed_when_it_began_and_its_end_on_the_same_entry(
    stalled: Stalled,  # noqa: F811
) -> None:
    """The download (held after its first block) began before a pause made meanwhile; the
    trail lists it first, running, then, once it ended, with its result and end."""
    ws, cell = stalled.ws, stalled.rig.directory
    await ws.send(call(3, "cell.pause"))
    assert "result" in await answer(ws, 3)
    await ws.send(call(4, "audit.list"))
    running = [
        e for e in (await answer(ws, 4))["result"] if e["method"] != "machines.out_of_service"
    ]
    assert [(e["method"], e["result"]) for e in running] == [
        ("mill.download", RUNNING),
        ("cell.pause", "ok"),
    ]
    download, pause = running
    assert download["at"] < pause["at"] and download["ended"] is None
    assert pause["ended"] is not None and pause["ended"] >= pause["at"]

    await stalled.rig.switch_off("cnc2:stall")  # the operator selects the link mode: READY
    done = await answer(ws, 2)
    assert done["result"]["message"] == "Download was correct", done
    with AuditLog(cell) as log:
        entries = [e for e in log.entries() if e.method != "machines.out_of_service"]
    assert [(e.method, e.result) for e in entries] == [
        ("mill.download", "ok"),
        ("cell.pause", "ok"),
    ]
    ended = entries[0]
    assert (ended.id, ended.at) == (download["id"], download["at"])  # the same entry, as begun
    assert ended.ended is not None and ended.ended > pause["ended"]


def test_a_running_entry_outlasts_pruning_and_readers_and_its_end_says_the_truth(
    tmp_path: Path,
) -> None:
    open_journal(tmp_path).close()
    with AuditLog(tmp_path) as log:
        began = log.begin("token:ann", "mill.download", {"machine": "cnc2"})
        for i in range(5):
            log.record(f"token:v{i}", "cell.estop", {}, "vera is a viewer: ...")
    # Another log (a restart, a command) prunes at its first entry: 2 others kept, and the
    # running one, whose end must find it. Opening it marked nothing.
    with AuditLog(tmp_path, keep_ok=2, keep_other=2) as log:
        log.record("token:v5", "cell.estop", {}, "vera is a viewer: ...")
        entries = log.entries()
    assert [(e.who, e.result) for e in entries] == [
        ("token:ann", RUNNING),
        ("token:v4", "vera is a viewer: ..."),
        ("token:v5", "vera is a viewer: ..."),
    ]
    # A controller starting while a command's own call ran would take it for cut: the end,
    # when it comes, says what happened.
    assert [e.id for e in mark_interrupted(tmp_path)] == [began.id]
    with AuditLog(tmp_path) as log:
        done = log.end(began, "ok")
        [entry] = [e for e in log.entries() if e.id == began.id]
    assert (entry.at, entry.result, entry.ended) == (began.at, "ok", done.ended)
    assert mark_interrupted(tmp_path) == []


#: The audit table as journals had it before ``ended`` (and a refusal counted on it).
OLD_AUDIT = """
CREATE TABLE audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT, at REAL NOT NULL, who TEXT NOT NULL,
    method TEXT NOT NULL, params TEXT NOT NULL, result TEXT NOT NULL,
    repeats INTEGER NOT NULL DEFAULT 1, last_at REAL
);
CREATE INDEX audit_by_at ON audit (at);
CREATE INDEX audit_by_caller ON audit (who, method, id);
INSERT INTO audit (at, who, method, params, result) VALUES
    (1700000000.0, 'token:ann', 'mill.download', '{"machine":"cnc2"}', 'ok');
INSERT INTO audit (at, who, method, params, result, repeats, last_at) VALUES
    (1700000010.0, 'token:vera', 'cell.pause', '{}', 'vera is a viewer: no', 3, 1700000030.0);
"""


def cli(cell: Path, *args: str) -> tuple[int, str]:
    result = CliRunner().invoke(cli_main, ["--cell", str(cell), *args])
    return result.exit_code, result.output


def test_an_old_journals_trail_still_opens_and_lists(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    open_journal(cell).close()
    shutil.copy(EXAMPLE / "cell.toml", cell)
    db = sqlite3.connect(cell / JOURNAL_FILE)
    with db:
        db.executescript(OLD_AUDIT)
    db.close()
    code, out = cli(cell, "audit", "--json")
    assert code == 0, out
    entries = json.loads(out)
    assert [(e["method"], e["result"], e["ended"]) for e in entries] == [
        ("mill.download", "ok", None),
        ("cell.pause", "vera is a viewer: no (and 2 times more in the next 20 s)", None),
    ]
    code, out = cli(cell, "audit")
    assert code == 0 and "Took" in out and "mill.download" in out, out
    # It goes on as a trail of today's.
    with AuditLog(cell) as log:
        began = log.begin("token:ann", "cell.estop", {"reason": "smoke"})
        log.end(began, "ok")
        last = log.entries()[-1]
    assert (last.method, last.result, last.at) == ("cell.estop", "ok", began.at)
    assert last.ended is not None
