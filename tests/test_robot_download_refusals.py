"""Downloads the host refuses before a byte goes out (a cycle running, a .rec the controller
would refuse), and refusals from the controller that leave the host's view as it was."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.errors import DeviceError, UsageError
from cellctl.kinds.ibm7545.aml import compile_source
from cellctl.kinds.ibm7545.driver import Ibm7545Robot
from cellctl.kinds.ibm7545.records import ProgramFile, Record
from cellctl.ui.cli import main

from .conftest import CELLCTL, Served, emulator_process

#: Runs until input 5 comes on; raises output 6 first (a cell program's "cycle done").
WAITS = "WRITEO(6, 1)\nWAITI(5, 1)\nEND\n"
OTHER = compile_source("DELAY(0)\nEND", "OTHER", 1)


def program(name: str = "TEST") -> ProgramFile:
    return compile_source(WAITS, name, 1)


# -- a download while a cycle runs -----------------------------------------------------------------


async def test_download_while_a_cycle_runs_is_refused_before_any_byte(robot_served: Served) -> None:
    async with await Ibm7545Robot.connect(robot_served.url, name="robot1") as robot:
        await robot.initialize()
        await robot.download(1, program())
        await robot.go(1)
        sent = robot.counters.transactions
        with pytest.raises(DeviceError) as err:
            await robot.download(2, OTHER)
        assert err.value.code == 48
        assert "refused by the host's state (robot state 2)" in str(err.value)
        assert "stop it first" in str(err.value)
        assert robot.counters.transactions == sent and robot_served.emulator.reject == 0
        # The host's view is what it was, and so is the controller: still running.
        assert robot.state == 2 and robot.partitions[1] == "TEST"
        assert robot_served.emulator.running
        await robot.stop()
        await robot.download(2, OTHER)
    assert robot_served.emulator.partitions[2] is not None


async def test_a_download_the_controller_refuses_keeps_the_hosts_view(robot_served: Served) -> None:
    """The host saw the cycle's "done" output (state 1, the cell's way) but the program still
    waits for input 5: the controller refuses the N with 48. That changes neither the host's
    state nor its partitions: the partition asked for keeps its program (no record reached it)."""
    async with await Ibm7545Robot.connect(robot_served.url, name="robot1") as robot:
        await robot.initialize()
        await robot.download(2, OTHER)
        await robot.download(1, program())
        await robot.go(1)
        await robot.wait_cycle_end(6, timeout=10, poll=0.01)
        assert robot.state == 1 and robot_served.emulator.running
        with pytest.raises(DeviceError, match="improper startup sequence") as err:
            await robot.download(2, program("NEW"))
        assert err.value.code == 48 and robot_served.emulator.reject == 48
        assert robot.state == 1
        assert robot.partitions == {1: "TEST", 2: "OTHER", 3: None, 4: None, 5: None}
        assert robot.holds(2, OTHER)
        assert (await robot.status()).machine.ok  # the line is in step
        robot_served.emulator.set_input(5, True)  # the program ends
        while robot_served.emulator.running:
            await robot.machine_status()
        await robot.download(2, program("NEW"))
        assert robot.partitions[2] == "NEW"


def robot_command(cell: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "--cell", str(cell), "robot", *args], capture_output=True, text=True, timeout=60
    )


@pytest.fixture
def emulator() -> Iterator[str]:
    with emulator_process("robot", "--listen", "pty", "--time-scale", "500", "--no-pacing") as url:
        yield url


def test_download_while_running_at_the_command_line(emulator: str, tmp_path: Path) -> None:
    """The defect: `download 2` while partition 1 ran said code 48 after sending, and
    `status` then showed state 0 and every partition Empty while the program still ran."""
    rec = tmp_path / "load1.rec"
    rec.write_text(program("LOAD1").to_text())
    for step in (["init"], ["download", "1", str(rec)], ["go", "1"]):
        done = robot_command(tmp_path, "--link", emulator, *step)
        assert done.returncode == 0, (step, done.stderr)
    refused = robot_command(tmp_path, "--link", emulator, "download", "2", str(rec))
    assert refused.returncode == 5  # as GO refused by the host's state
    assert "improper startup sequence (code 48)" in refused.stderr
    assert "refused by the host's state" in refused.stderr and "stop it first" in refused.stderr
    status = robot_command(tmp_path, "--link", emulator, "status")
    assert status.returncode == 0, status.stderr
    assert "2 (Executing)" in status.stdout
    assert "Full (LOAD1)" in status.stdout


# -- a .rec the controller would refuse -----------------------------------------------------------

N_RECORD = "N09015846455231202020C7"  # partition 1, XFER1


@pytest.mark.parametrize(
    ("record", "fault"),
    [
        ("D01FFFF", "unknown opcode 0xff"),
        ("D030763016B", "WAITI with port 99, value 1 out of range (port 1..16, value 0 or 1)"),
        ("D030900050E", "BRANCH to instruction 5 outside the program (instructions 0..1)"),
        ("D02010001", "PMOVE record has the wrong length"),
    ],
    ids=["opcode-ff", "waiti-port-99", "branch-past-end", "short-pmove"],
)
def test_a_rec_with_an_instruction_the_controller_refuses_is_refused(
    tmp_path: Path, record: str, fault: str
) -> None:
    bad = tmp_path / "bad.rec"
    bad.write_text(f"{N_RECORD}\n\n{record}\nD010A0A\nE0000\n")
    with pytest.raises(UsageError) as err:
        ProgramFile.load(bad)
    assert str(err.value) == f"{bad}, line 3: instruction 0 ({record}): {fault}"
    result = CliRunner().invoke(main, ["robot", "--link", "loop://", "download", "1", str(bad)])
    assert result.exit_code == 2 and f"line 3: instruction 0 ({record})" in result.output


def test_a_rec_without_instructions_is_refused(tmp_path: Path) -> None:
    empty = tmp_path / "empty.rec"
    empty.write_text(f"{N_RECORD}\nE0000\n")
    with pytest.raises(UsageError, match="no instructions between the N record and E0000"):
        ProgramFile.load(empty)


async def test_a_bad_rec_never_reaches_the_controller(robot_served: Served, tmp_path: Path) -> None:
    bad = tmp_path / "bad.rec"
    bad.write_text(f"{N_RECORD}\nD01FFFF\nE0000\n")
    async with await Ibm7545Robot.connect(robot_served.url) as robot:
        await robot.initialize()
        sent = robot.counters.transactions
        with pytest.raises(UsageError, match="unknown opcode 0xff"):
            await robot.download(1, bad)
        assert robot.counters.transactions == sent and robot.counters.download_retries == 0
    assert robot_served.emulator.reject == 0 and robot_served.emulator.partitions[1] is None


async def test_a_record_format_error_for_the_content_is_not_sent_again(
    robot_served: Served,
) -> None:
    """A program built in memory is not a file: the controller decodes it at its end record
    and refuses it with 16. The same record refused twice is its content, not the line: the
    host stops there instead of sending it download_retries (3) times."""
    built = ProgramFile.build("BAD", 1, [Record("D", b"\xff"), Record("D", b"\x0a")])
    async with await Ibm7545Robot.connect(robot_served.url) as robot:
        await robot.initialize()
        with pytest.raises(DeviceError) as err:
            await robot.download(1, built)
        assert err.value.code == 16
        assert "record 4 (E0000) refused twice in a row: its content" in str(err.value)
        assert robot.counters.download_retries == 1
        assert robot.partitions[1] is None
        assert (await robot.status()).machine.ok
