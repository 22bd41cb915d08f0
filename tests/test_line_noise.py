"""Downloads survive a noisy line: the ``noise`` fault of the serving layer, and the robot
driver sending a download again from its N record after a transmission error."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from cellctl.emulators.serve import LineNoise, serve
from cellctl.errors import CellctlError, DeviceError, UsageError
from cellctl.kinds.ibm7545.aml import compile_source, decode_program
from cellctl.kinds.ibm7545.driver import Ibm7545Robot, RobotConfig
from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator, LoadedProgram
from cellctl.kinds.ibm7545.records import ProgramFile
from cellctl.link import ROBOT_LINE

from .conftest import CELLCTL

RATE = 3e-4
RUNS = 50
SEED = 2  # the same bytes garbled on every run of the test: it repeats exactly
CONFIG = RobotConfig(reply_timeout=0.3, retry_settle=0.05)
#: A download of 99 records may take each try's every record to its deadline, and no more.
DEADLINE_S = (CONFIG.download_retries + 1) * (99 * CONFIG.reply_timeout + 1.0)


def program(run: int) -> ProgramFile:
    """99 records (N, 97 instructions, end), different for every run."""
    lines = [
        "DELAY(0)" if i % 4 == 3 else f"PMOVE(PT({300 + (i + run) % 50}, {i % 40 - 20}, 0, 0))"
        for i in range(96)
    ]
    prog = compile_source("\n".join([*lines, "END"]), f"RUN{run}", 1)
    assert len(prog.records) == 99
    return prog


def held(emulator: Ibm7545Emulator, partition: int) -> LoadedProgram | None:
    return emulator.partitions[partition]


async def test_downloads_through_a_noisy_line_complete_or_fail_typed(tmp_path: Path) -> None:
    emulator = Ibm7545Emulator(time_scale=1000.0)
    server = await serve(emulator, "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    completed = retried = 0
    try:
        async with await Ibm7545Robot.connect(server.url, config=CONFIG) as robot:
            await robot.initialize()
            emulator.set_fault("noise", f"{RATE},{SEED}")
            for run in range(RUNS):
                prog = program(run)
                partition = run % 5 + 1
                emulator.partitions[partition] = None
                retries: list[str] = []
                started = time.monotonic()
                try:
                    async with asyncio.timeout(DEADLINE_S):
                        await robot.download(
                            partition,
                            prog,
                            on_retry=lambda a, n, e, seen=retries: seen.append(f"{a}/{n}"),
                        )
                except CellctlError:
                    assert robot.partitions[partition] is None  # never trusted half-sent
                    if robot.state != 1:  # a reject that left it cold: set it up again
                        emulator.clear_fault("noise")
                        await robot.initialize()
                        emulator.set_fault("noise", f"{RATE},{SEED}")
                else:
                    completed += 1
                    body = prog.with_partition(partition).records[1:-1]
                    assert held(emulator, partition) == LoadedProgram(
                        prog.name, tuple(decode_program(body))
                    ), f"run {run}: success reported, but the partition holds something else"
                    assert robot.holds(partition, prog)
                assert time.monotonic() - started < DEADLINE_S
                retried += len(retries)
                assert retries == [f"{i}/3" for i in range(1, len(retries) + 1)]
            assert robot.counters.download_retries == retried
    finally:
        await server.close()
    assert emulator.noise is not None and emulator.noise.flipped + emulator.noise.dropped > 0
    assert completed >= 0.9 * RUNS, f"{completed} of {RUNS} completed, {retried} retries"
    assert retried > 0


async def test_a_reject_that_is_not_about_transmission_is_not_retried() -> None:
    emulator = Ibm7545Emulator(time_scale=1000.0, max_instructions=10)
    server = await serve(emulator, "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    try:
        async with await Ibm7545Robot.connect(server.url, config=CONFIG) as robot:
            await robot.initialize()
            with pytest.raises(DeviceError) as err:
                await robot.download(2, program(0))
            assert err.value.code == 80  # insufficient memory
            assert robot.counters.download_retries == 0
            assert robot.partitions[2] is None
    finally:
        await server.close()


def test_line_noise_flips_or_drops_at_its_rate() -> None:
    clean = bytes(range(256)) * 40
    assert LineNoise(0.0, 1).garble(clean, "in") == clean
    noisy = LineNoise(0.5, 1)
    out = noisy.garble(clean, "out")
    assert noisy.dropped + noisy.flipped > 0.4 * len(clean)
    assert len(out) == len(clean) - noisy.dropped
    again = LineNoise(0.5, 1)
    assert again.garble(clean, "out") == out  # a seed repeats the run
    for bad in ("", "x", "2", "-1", "nan", "1e-3,x"):
        with pytest.raises(UsageError):
            LineNoise.parse(bad)
    assert LineNoise.parse("3e-4,7").seed == 7


@pytest.mark.parametrize("machine", ["robot", "mill"])
def test_emulator_help_lists_the_noise_fault(machine: str) -> None:
    import subprocess

    out = subprocess.run(
        [*CELLCTL, "emulate", machine, "--help"], capture_output=True, text=True, timeout=60
    ).stdout
    assert "noise: =RATE[,SEED]" in out
