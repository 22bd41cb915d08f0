"""Every single-machine `cellctl emulate ...` says, after where it listens, each fault switch
it runs with, in `emulate cell`'s words: a default taken is named ("fault drop on (5 lines,
its default)"), an argument given is shown ("fault noise=3e-4,7 on"). Each runs in its own
process and is stopped with Ctrl-C (SIGINT)."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from .conftest import CELLCTL

#: Seconds an emulator may take to start and say its faults (a busy box, a cold import).
START_S = 60.0
#: Seconds it may take to stop once told to.
STOP_S = 20.0

UR_PORTS = ["--dashboard-port", "0", "--secondary-port", "0", "--rtde-port", "0"]


@pytest.mark.parametrize(
    ("args", "what", "said"),
    [
        (
            ["robot", "--fault", "corrupt-checksum", "--fault", "noise=3e-4,7"],
            "IBM 7545 emulator",
            ["fault corrupt-checksum on (1 record, its default)", "fault noise=3e-4,7 on"],
        ),
        (
            # Many robots take the same switches: said once, after every machine's link.
            ["robot", "--count", "2", "--fault", "corrupt-checksum", "--fault", "drop"],
            "IBM 7545 emulator",
            ["fault corrupt-checksum on (1 record, its default)", "fault drop on"],
        ),
        (
            ["mill", "--fault", "drop", "--fault", "noise=3e-4,7"],
            "Dyna 2400 mill emulator",
            ["fault drop on (5 lines, its default)", "fault noise=3e-4,7 on"],
        ),
        (
            ["iso-cnc", "--fault", "parity-noise", "--fault", "line-lag=40"],
            "ISO-code CNC control emulator",
            ["fault parity-noise on (0.01, its default)", "fault line-lag=40 on"],
        ),
        (
            # No UR switch takes an argument: two plain ones.
            ["ur", *UR_PORTS, "--fault", "local_mode", "--fault", "never_ends"],
            "UR emulator",
            ["fault local_mode on", "fault never_ends on"],
        ),
        (
            [
                "plc",
                "--listen",
                "modbus://127.0.0.1:0",
                "--fault",
                "slow",
                "--fault",
                "stuck-door=2",
            ],
            "PLC emulator",
            ["fault slow on (400 ms, its default)", "fault stuck-door=2 on"],
        ),
    ],
    ids=["robot", "robot-count", "mill", "iso-cnc", "ur", "plc"],
)
def test_an_emulator_says_the_faults_it_runs_with(
    tmp_path: Path, args: list[str], what: str, said: list[str]
) -> None:
    expected = [f"  {line}" for line in said]
    errors = tmp_path / "stderr"
    with errors.open("w") as stderr:
        proc = subprocess.Popen(
            [*CELLCTL, "--cell", str(tmp_path / "cell"), "emulate", *args],
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
            cwd=tmp_path,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
    try:
        rows = _rows(proc)
        seen = _read(rows, until=lambda line: line == expected[-1], within=START_S)
        assert seen[-1:] == expected[-1:], _story(args, seen, errors)
        proc.send_signal(signal.SIGINT)
        seen += _read(rows, until=lambda line: False, within=STOP_S)
        proc.wait(timeout=STOP_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == 0, _story(args, seen, errors)
    # Where it listens first; its faults the last it says at start, in the order given.
    assert "listening on" in seen[0] or what in seen[0], _story(args, seen, errors)
    assert [line for line in seen if line.startswith("  fault ")] == expected, seen
    assert seen[-3:] == [*expected, f"{what} stopped"], _story(args, seen, errors)


def test_a_bad_switch_is_refused_before_any_machine_is_served(tmp_path: Path) -> None:
    """Checked once, before a fleet's workers start, in the emulator's words."""
    fleet = ["--count", "2", "--workers", "2"]
    done = subprocess.run(
        [*CELLCTL, "emulate", "robot", *fleet, "--fault", "corrupt-checksum=x"],
        capture_output=True,
        text=True,
        timeout=START_S,
        cwd=tmp_path,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "corrupt-checksum needs a count, not 'x'" in done.stderr
    assert "drive it with" not in done.stdout


def _rows(proc: subprocess.Popen[str]) -> queue.Queue[str | None]:
    """The process's output lines as they come (None at its end): read in a thread, so each
    wait for one has a deadline."""
    rows: queue.Queue[str | None] = queue.Queue()

    def read() -> None:
        assert proc.stdout is not None
        for row in proc.stdout:
            rows.put(row.rstrip("\n"))
        rows.put(None)

    threading.Thread(target=read, daemon=True).start()
    return rows


def _read(rows: queue.Queue[str | None], until: Callable[[str], bool], within: float) -> list[str]:
    """Lines from ``rows`` up to the first for which ``until(line)`` is true, or the output's
    end, or ``within`` seconds, whichever comes first."""
    seen: list[str] = []
    deadline = time.monotonic() + within
    while (left := deadline - time.monotonic()) > 0:
        try:
            line = rows.get(timeout=left)
        except queue.Empty:
            break
        if line is None:
            break
        seen.append(line)
        if until(line):
            break
    return seen


def _story(args: list[str], seen: list[str], errors: Path) -> str:
    """What a failed check shows: the command, what it said, what it complained of."""
    said = "\n".join(seen)
    return f"cellctl emulate {' '.join(args)} said:\n{said}\nstderr:\n{errors.read_text()}"
