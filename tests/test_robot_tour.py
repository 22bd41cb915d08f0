"""README's robot tour with no PLC: a program in WAITI says what it waits for, `robot io set`
drives the emulator's input through the real link (a pty between two processes), and the
program goes on; a real controller's refusal of that emulator-only operand says why."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.errors import DeviceError
from cellctl.kinds.ibm7545.aml import Op, decode_program
from cellctl.kinds.ibm7545.driver import Ibm7545Robot
from cellctl.kinds.ibm7545.records import ProgramFile
from cellctl.testing import expected_exchange
from cellctl.ui.cli import main

from .conftest import emulator_process

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
HINT = re.compile(r"`robot io set (\d+) (on|off)`")


@pytest.fixture
def emulator() -> Iterator[str]:
    with emulator_process("robot", "--listen", "pty", "--time-scale", "500", "--no-pacing") as url:
        yield url


@dataclass
class Ran:
    returncode: int
    stdout: str
    stderr: str


def robot(cell: Path, *args: str) -> Ran:
    """``cellctl --cell CELL robot ARGS`` in this process (the emulator runs in its own, the
    pty between them): a new Python for each command is slow on a loaded box."""
    result = CliRunner().invoke(main, ["--cell", str(cell), "robot", *args])
    return Ran(result.exit_code, result.stdout, result.stderr)


def outputs(cell: Path, link: str) -> list[str]:
    """The DO row of `robot io`: "1" or "." for outputs 1 to 16."""
    found = robot(cell, "--link", link, "io")
    assert found.returncode == 0, found.stderr
    for line in found.stdout.splitlines():
        cells = [c.strip() for c in re.split(r"[│|┃]", line) if c.strip()]
        if cells and cells[0] == "DO":
            return cells[1:]
    raise AssertionError(found.stdout)


def test_the_tour_names_each_input_it_waits_for_and_io_set_drives_it(
    emulator: str, tmp_path: Path
) -> None:
    rec = tmp_path / "load1.rec"
    source = EXAMPLES / "robot" / "conveyor_to_cnc1.aml"
    assert robot(tmp_path, "compile", str(source), "-o", str(rec)).returncode == 0
    program = decode_program(ProgramFile.load(rec).body)
    waits = [(i.operands[0], i.operands[1]) for i in program if i.op is Op.WAITI]
    assert robot(tmp_path, "--link", emulator, "init").returncode == 0
    assert robot(tmp_path, "--link", emulator, "download", "1", str(rec)).returncode == 0
    assert robot(tmp_path, "--link", emulator, "go", "1").returncode == 0
    told: list[tuple[int, int]] = []
    deadline = time.monotonic() + 60
    while True:
        assert time.monotonic() < deadline, f"still waiting after {told}"
        status = robot(tmp_path, "--link", emulator, "status")
        assert status.returncode == 0, status.stderr
        hint = HINT.search(status.stdout)
        if hint is None:
            break
        assert "waits for input" in status.stdout and "`robot stop` ends the cycle" in status.stdout
        line, value = int(hint.group(1)), hint.group(2)
        told.append((line, 1 if value == "on" else 0))
        done = robot(tmp_path, "--link", emulator, "io", "set", str(line), value)
        assert done.returncode == 0, done.stderr
        assert f"input {line} {value}" in done.stdout
    # The status named the program's WAITIs in order, each once, and the inputs show them.
    assert told == list(dict.fromkeys(waits))
    # Past its last WAITI the program closed the vise (output 1): it went on to its END.
    cut = time.monotonic() + 30
    while outputs(tmp_path, emulator)[0] != "1":
        assert time.monotonic() < cut, outputs(tmp_path, emulator)


def test_robot_stop_ends_a_program_waiting_in_waiti(emulator: str, tmp_path: Path) -> None:
    rec = tmp_path / "load1.rec"
    robot(tmp_path, "compile", str(EXAMPLES / "robot" / "conveyor_to_cnc1.aml"), "-o", str(rec))
    assert robot(tmp_path, "--link", emulator, "init").returncode == 0
    assert robot(tmp_path, "--link", emulator, "download", "1", str(rec)).returncode == 0
    assert robot(tmp_path, "--link", emulator, "go", "1").returncode == 0
    assert "waits for input 1 on" in robot(tmp_path, "--link", emulator, "status").stdout
    stopped = robot(tmp_path, "--link", emulator, "stop")
    assert stopped.returncode == 0 and "Cycle stopped" in stopped.stdout
    after = robot(tmp_path, "--link", emulator, "status")
    assert re.search(r"Robot state +│ 1 ", after.stdout) and "waits for" not in after.stdout


def test_io_set_is_refused_before_a_byte_for_a_bad_line(tmp_path: Path) -> None:
    bad = robot(tmp_path, "--link", "loop://", "io", "set", "17", "on")
    assert bad.returncode == 2 and "17" in bad.stderr


async def test_a_real_controller_refuses_io_set_and_the_error_says_why() -> None:
    ready, eot = b"\x13\x11", b"\x04"
    # X, then the emulator-only operand 41 (input 1 on); a 7545 answers EOT, and its reject
    # status (R 02) is 32, undefined record (D01 20 20).
    script = [
        (b"X", ready),
        (b"41\r\n", eot),
        (b"R", ready),
        (b"02\r\n", b"D012020\r\n"),
        (b"\x06", b"EG\r\n"),
        (b"\x06", b""),
    ]
    async with expected_exchange(script) as link:
        with pytest.raises(DeviceError) as err:
            await Ibm7545Robot(link).set_input(1, True)
    assert err.value.code == 32 and "undefined record" in str(err.value)
    assert "its inputs from its wiring" in str(err.value)
