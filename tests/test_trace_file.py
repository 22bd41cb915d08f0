"""``--trace FILE`` as a user meets it: a trace is never appended to a file that holds
something else (the program being sent above all), refused before a byte goes out; a trace
that cannot be written stops with one warning while the work goes on, never a traceback."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from cellctl.errors import UsageError
from cellctl.link import ROBOT_LINE, SENT, TrafficLog, open_link
from cellctl.link.trace import refuse_trace_on_inputs

from .test_robot_cli import emulator, robot  # noqa: F401  (emulator is a fixture)

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@pytest.fixture
def program(tmp_path: Path) -> Path:
    rec = tmp_path / "load1.rec"
    aml = EXAMPLES / "robot" / "conveyor_to_cnc1.aml"
    compiled = robot(tmp_path, "compile", str(aml), "-o", str(rec))
    assert compiled.returncode == 0, compiled.stderr
    return rec


def test_trace_onto_the_program_being_sent_is_refused_before_a_byte(
    emulator: str,  # noqa: F811  (the fixture of test_robot_cli)
    tmp_path: Path,
    program: Path,
) -> None:
    before = program.read_bytes()
    assert robot(tmp_path, "--link", emulator, "init").returncode == 0
    link = tmp_path / "same.rec"
    link.symlink_to(program)
    for trace in (str(program), str(link), f"{tmp_path}/./load1.rec"):
        down = robot(tmp_path, "--link", emulator, "--trace", trace, "download", "5", str(program))
        assert down.returncode == 2, down.stderr
        assert f"trace file {trace} is {program}, which this command reads" in down.stderr
        assert "Traceback" not in down.stderr
    assert program.read_bytes() == before  # not a line added
    status = robot(tmp_path, "--link", emulator, "status")
    assert "Partition 5" in status.stdout and "Empty" in status.stdout.split("Partition 5")[1]
    # The program still downloads, and a trace of its own is appended to run after run.
    trace = tmp_path / "robot.trace"
    for _ in range(2):
        down = robot(
            tmp_path, "--link", emulator, "--trace", str(trace), "download", "5", str(program)
        )
        assert down.returncode == 0, down.stderr
    assert trace.read_text().count(">>  4E") == 2


def test_trace_on_a_full_device_warns_once_and_the_work_is_done(
    emulator: str,  # noqa: F811  (the fixture of test_robot_cli)
    tmp_path: Path,
    program: Path,
) -> None:
    assert robot(tmp_path, "--link", emulator, "init").returncode == 0
    down = robot(
        tmp_path, "--link", emulator, "--trace", "/dev/full", "download", "3", str(program)
    )
    assert down.returncode == 0, down.stderr
    assert "Download was correct" in down.stdout
    assert "Traceback" not in down.stderr
    warned = [line for line in down.stderr.splitlines() if "trace file /dev/full" in line]
    assert warned == [
        "trace file /dev/full: cannot write it (No space left on device): the trace stops "
        "here; the link carries on"
    ]
    assert "Full" in robot(tmp_path, "--link", emulator, "status").stdout


async def test_a_failed_trace_write_keeps_the_link_and_the_memory_log() -> None:
    log = TrafficLog("/dev/full")
    async with await open_link("loop://", ROBOT_LINE, trace=log, label="robot1") as link:
        await link.write(b"R")
        assert await link.read(timeout=1) == b"R"
        await link.write(b"S")
    assert log.error is not None and "No space left on device" in log.error
    assert log.sent("robot1") == b"RS"
    log.close()  # what was still buffered is dropped: no second error


def test_an_existing_trace_is_appended_to_and_anything_else_refused(tmp_path: Path) -> None:
    trace = tmp_path / "cnc1.trace"
    for n in range(2):
        log = TrafficLog(trace)
        log.record("cnc1", SENT, b"%", 1_800_000_000.0 + n)
        log.close()
    assert trace.read_text().count("cnc1 >>  25") == 2
    assert oct(trace.stat().st_mode & 0o777) == "0o600"
    config = tmp_path / "cell.toml"
    config.write_text('[machines.cnc1]\nkind = "dyna2400"\n')
    with pytest.raises(UsageError, match="holds something other than a cellctl trace"):
        TrafficLog(config)
    assert config.read_text() == '[machines.cnc1]\nkind = "dyna2400"\n'
    empty = tmp_path / "new.trace"
    empty.touch()
    TrafficLog(empty).close()  # an empty file is a trace yet to be written


def test_refuse_trace_on_inputs_compares_files_not_names(tmp_path: Path) -> None:
    program = tmp_path / "O1234.nc"
    program.write_text("%\nO1234\nM30\n%\n")
    alias = tmp_path / "alias.nc"
    alias.symlink_to(program)
    os.link(program, tmp_path / "hard.nc")
    for trace in (program, alias, tmp_path / "hard.nc", tmp_path / "sub" / ".." / "O1234.nc"):
        (tmp_path / "sub").mkdir(exist_ok=True)
        with pytest.raises(UsageError, match=f"trace file {trace} is {program}"):
            refuse_trace_on_inputs(trace, [tmp_path / "other.nc", program])
    refuse_trace_on_inputs(tmp_path / "mill.trace", [program])  # not there yet
    refuse_trace_on_inputs(None, [program])
    (tmp_path / "other.nc").write_text("%\n")
    refuse_trace_on_inputs(tmp_path / "other.nc", [program, tmp_path / "missing.nc"])
