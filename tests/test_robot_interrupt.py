"""An interrupted download leaves the line in step: the controller is not left half-way
through receiving a program, deaf to the next command.

The emulator runs on machine time (x1): it waits the spec's 30 s for a record that does not
come, so a host that just went away would find it deaf for that long. The line is paced at
4800 baud over a real pty, so a download of 200 records takes seconds and is cut mid-way.
"""

from __future__ import annotations

import asyncio
import signal
from pathlib import Path

import pytest

from cellctl.drivers.state import StateStore, machine_key
from cellctl.emulators.serve import Server, serve
from cellctl.kinds.ibm7545.aml import compile_source
from cellctl.kinds.ibm7545.driver import Ibm7545Robot
from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator
from cellctl.kinds.ibm7545.records import ProgramFile
from cellctl.link import ROBOT_LINE

from .conftest import CELLCTL

#: A hang guard, not a timing figure: far above the resync's own deadline.
GUARD_S = 30.0


def big_program() -> ProgramFile:
    """200 records of 25 characters: about 11 s at 4800 baud."""
    moves = [f"PMOVE(PT({300 + i % 50}, {i % 40 - 20}, 0, 0))" for i in range(197)]
    return compile_source("\n".join([*moves, "END"]), "BIG", 1)


SMALL = compile_source("DELAY(0)\nEND", "SMALL", 1)


async def paced_robot() -> tuple[Ibm7545Emulator, Server]:
    emulator = Ibm7545Emulator()  # machine time: its host timeout is the spec's 30 s
    return emulator, await serve(emulator, "pty", ROBOT_LINE, pacing=True)


async def test_a_cancelled_download_resyncs_before_it_gives_up(tmp_path: Path) -> None:
    emulator, server = await paced_robot()
    store = StateStore(tmp_path)
    try:
        async with await Ibm7545Robot.connect(server.url, name="robot1", store=store) as robot:
            await robot.initialize()
            underway = asyncio.Event()

            def progress(records: int, total: int, sent: int) -> None:
                if records >= 5:
                    underway.set()

            task = asyncio.ensure_future(robot.download(4, big_program(), progress=progress))
            async with asyncio.timeout(GUARD_S):
                await underway.wait()
                task.cancel()  # what Ctrl-C does to the command's task
                with pytest.raises(asyncio.CancelledError):
                    await task
            assert robot.partitions[4] is None  # never trusted half-sent
            assert store.load(machine_key("robot1"))["out_of_step"] is False  # in step now
            assert (await robot.status()).machine.ok  # the same driver goes on
        # The next command, as the next `cellctl robot` process opens the robot.
        async with await Ibm7545Robot.connect(server.url, name="robot1", store=store) as again:
            assert (await again.status()).machine.ok
            await again.download(4, SMALL)
    finally:
        await server.close()
    program = emulator.partitions[4]
    assert program is not None and program.name == "SMALL"


async def robot_command(*args: str) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, "robot", *args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    async with asyncio.timeout(60):
        out, err = await proc.communicate()
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


@pytest.mark.parametrize(
    ("sig", "code"),
    [(signal.SIGINT, 130), (signal.SIGTERM, 130), (signal.SIGKILL, -signal.SIGKILL)],
    ids=["ctrl-c", "sigterm", "killed"],
)
async def test_status_works_after_an_interrupted_download_at_the_command_line(
    tmp_path: Path, sig: signal.Signals, code: int
) -> None:
    """The defect: after Ctrl-C on `download 4 big.rec`, `status` said "no answer from the
    robot controller". Ctrl-C resyncs inside the interruption; a killed process cannot, and
    the next command resyncs first (the host state saved that the line is out of step)."""
    rec = tmp_path / "big.rec"
    rec.write_text(big_program().to_text())
    trace = tmp_path / "download.trace"
    emulator, server = await paced_robot()
    try:
        link = ("--link", server.url)
        assert (await robot_command(*link, "init"))[0] == 0
        proc = await asyncio.create_subprocess_exec(
            *CELLCTL, "robot", *link, "--trace", str(trace), "download", "4", str(rec),
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        async with asyncio.timeout(GUARD_S):
            # Mid-way: the N record and a few D records out (one ">>" row a write).
            while not trace.exists() or trace.read_text().count(">>") < 8:
                assert proc.returncode is None, "the download ended before it was interrupted"
                await asyncio.sleep(0.05)
            proc.send_signal(sig)
            _, err = await proc.communicate()
        assert proc.returncode == code, err.decode()
        if code == 130:  # SIGTERM as Ctrl-C: it used to end with 143, no word, out of step
            assert err.decode().strip().splitlines()[-1] == "interrupted", err.decode()
        rc, out, err_text = await robot_command(*link, "status")
        assert rc == 0, err_text
        assert "Robot state" in out and "Partition 4" in out
        small = tmp_path / "small.rec"
        small.write_text(SMALL.to_text())
        rc, out, err_text = await robot_command(*link, "download", "4", str(small))
        assert rc == 0 and "Download was correct" in out, err_text
    finally:
        await server.close()
    program = emulator.partitions[4]
    assert program is not None and program.name == "SMALL"
