"""The running cell as a service, as a user meets it: ``cellctl run`` cutting an order while a
second shell asks the robot and a mill for their status, tries a manual function, and starts
a second controller. Every process is a real ``cellctl``; the API is the cell's Unix socket (and
TCP on loopback, which the run log names beside it)."""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellctl.cell.journal import open_journal
from cellctl.mailbox import open_mailbox

from .conftest import CELLCTL, emulated_cell_process, free_port, wait_until

TIME_SCALE = "400"
READ_LIMIT = 1.0


def cellctl(cell: Path, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "--cell", str(cell), *args], capture_output=True, text=True, timeout=timeout
    )


@pytest.fixture
def running_cell(tmp_path: Path) -> Iterator[tuple[Path, subprocess.Popen[str]]]:
    """An emulated cell and ``cellctl run`` on it, each in its own process."""
    with emulated_cell_process(tmp_path / "cell", TIME_SCALE) as cell:
        # A look at the robot or the PLC may take READ_LIMIT s before it counts as not
        # answering (half the 0.1 s poll period by default): on a box shared with other
        # work, the emulator's process is not always scheduled within 50 ms.
        toml = cell / "cell.toml"
        text = toml.read_text()
        assert "[cell]\n" in text
        text = text.replace("[cell]\n", f"[cell]\nread_limit = {READ_LIMIT}\n", 1)
        # The API on TCP too: the cell's own commands still go through its socket.
        toml.write_text(text + f'\n[api]\nlisten = "127.0.0.1:{free_port()}"\n')
        with open_mailbox(cell) as mailbox:
            mailbox.post_order("wax-robot-base", 2, order_id="A")
        log = (tmp_path / "run.log").open("w")
        # Output to a file: the plain event log, a line at a time, is the default there.
        run = subprocess.Popen(
            [*CELLCTL, "--cell", str(cell), "run"], stdout=log, stderr=subprocess.STDOUT, text=True
        )
        try:
            wait_until(lambda: (cell / "api.sock").exists(), "the API socket")
            yield cell, run
        finally:
            if run.poll() is None:
                run.send_signal(signal.SIGINT)
                try:
                    run.wait(60)
                except subprocess.TimeoutExpired:
                    run.kill()


def cuts(cell: Path) -> list[str]:
    with open_journal(cell) as journal:
        return [s.state for s in journal.steps() if s.kind == "machine"]


def test_status_from_a_second_shell_does_not_disturb_the_cut(
    running_cell: tuple[Path, subprocess.Popen[str]],
) -> None:
    cell, run = running_cell
    log = cell.parent / "run.log"
    wait_until(lambda: "order A accepted" in log.read_text(), "the event log, as it happens")
    port = (cell / "cell.toml").read_text().split('listen = "127.0.0.1:', 1)[1].split('"')[0]
    # The run log names both places the API answers: the socket and the TCP address.
    assert f"control API on {cell / 'api.sock'} and http://127.0.0.1:{port}" in log.read_text()
    assert run.poll() is None
    wait_until(lambda: "started" in cuts(cell), "a cut in flight")
    for _ in range(3):
        robot = cellctl(cell, "robot", "robot", "status")
        assert robot.returncode == 0, robot.stderr
        assert "Robot state" in robot.stdout and "Partition 1" in robot.stdout
        mill = cellctl(cell, "mill", "cnc1", "status")
        assert mill.returncode == 0, mill.stderr
        assert "cnc1: state" in mill.stdout
    manual = cellctl(cell, "robot", "robot", "home")
    assert manual.returncode == 6
    assert "in automatic service: take it out first" in manual.stderr
    second = cellctl(cell, "run", "--no-live")
    assert second.returncode == 6
    assert f"cellctl run (pid {run.pid})" in second.stderr
    with open_mailbox(cell) as mailbox:
        wait_until(lambda: mailbox.get_order("A").state == "done", "order A done", timeout=120)
    with open_journal(cell) as journal:
        assert not journal.alarms(), [a.text for a in journal.alarms()]
        assert not journal.parts(statuses=["held"])
        machine_steps = [s for s in journal.steps() if s.kind == "machine"]
        assert len(machine_steps) == 4 and all(s.state == "finished" for s in machine_steps)
    assert run.poll() is None  # still running, nothing wedged


def test_operator_takes_cnc2_out_runs_it_by_hand_and_returns_it(
    running_cell: tuple[Path, subprocess.Popen[str]],
) -> None:
    cell, run = running_cell
    out = cellctl(cell, "machine", "cnc2", "out", "--reason", "check the tool")
    assert out.returncode == 0 and "cnc2 out of automatic service" in out.stdout
    wait_until(lambda: any(s == "finished" for s in cuts(cell)), "cnc1 cuts while cnc2 is out")
    wait_until(lambda: cellctl(cell, "mill", "cnc2", "status").returncode == 0, "cnc2 answers")
    status = cellctl(cell, "mill", "cnc2", "status")
    assert "state 2 (Initialized)" in status.stdout
    traffic = cellctl(cell, "traffic", "cnc2")
    assert traffic.returncode == 0 and (">>" in traffic.stdout or "<<" in traffic.stdout)
    back = cellctl(cell, "machine", "cnc2", "in")
    assert back.returncode == 0 and "back in automatic service" in back.stdout
    with open_mailbox(cell) as mailbox:
        wait_until(lambda: mailbox.get_order("A").state == "done", "order A done", timeout=120)
    # What the controller wrote to its journal is what another process reads there.
    wait_until(lambda: cuts(cell) == ["finished"] * 4, "4 cuts finished, in the journal")
    listed = cellctl(cell, "orders")
    assert listed.returncode == 0 and "done" in listed.stdout
    os.kill(run.pid, signal.SIGINT)
    assert run.wait(60) == 0


def test_traffic_follow_prints_new_bytes_as_they_pass(
    running_cell: tuple[Path, subprocess.Popen[str]],
) -> None:
    """``traffic --follow`` through the controller: rows keep coming while the cell polls,
    each shown once, until the user stops it."""
    cell, _ = running_cell
    out = cell.parent / "follow.out"
    with out.open("w") as sink:
        follow = subprocess.Popen(
            [
                *CELLCTL,
                "--cell",
                str(cell),
                "traffic",
                "robot",
                "--follow",
                "--json",
                "--limit",
                "200",
            ],
            stdout=sink,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            wait_until(
                lambda: len(out.read_text().splitlines()) >= 300,
                "more than a tail of rows followed",
            )
        finally:
            follow.send_signal(signal.SIGINT)
            follow.wait(30)
    rows = out.read_text().splitlines()
    seen = [r for r in rows if r.startswith("{")]
    assert len(seen) >= 300 and len(set(seen)) == len(seen), rows[:5]
    assert (follow.returncode, rows[-1]) == (130, "interrupted"), rows[-3:]
