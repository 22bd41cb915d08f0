"""`cellctl emulate cell --fault cnc1:stall`: the stall comes in the middle of cnc1's first cut,
not after its setup block (the first block the mill runs, which it used to take every time).

The mill emulator's stall: READY never comes after the block running when it is switched on.
Given at start, it is switched on as cnc1's first cut starts; the controller then finds the
cut still running at its block's deadline, holds the part ("needs inspection") and raises one
alarm on cnc1, with no setup alarm before it. The real commands, each in its own process:
`cellctl emulate cell` and `cellctl run`."""

from __future__ import annotations

import asyncio
import re
import signal
from pathlib import Path

import pytest

from cellctl.cell.journal import JOURNAL_FILE, Journal
from cellctl.mailbox import open_mailbox
from tests.conftest import CELLCTL, until

#: The emulated cell's time scale: a cut of minutes in a few seconds, and the deadlines it
#: writes at their floor (5 s).
TIME_SCALE = "1000"


@pytest.mark.timeout(240)
async def test_a_stall_given_at_start_stalls_the_first_cut_not_the_setup(
    tmp_path: Path,
) -> None:
    cell = tmp_path / "cell"
    emulate = await asyncio.create_subprocess_exec(
        *CELLCTL, "--cell", str(cell), "emulate", "cell", "--time-scale", TIME_SCALE,
        "--fault", "cnc1:stall",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
    )  # fmt: skip
    run: asyncio.subprocess.Process | None = None
    try:
        assert emulate.stdout is not None
        said = []
        async with asyncio.timeout(60):  # every machine listens once the PLC's line is out
            while line := (await emulate.stdout.readline()).decode():
                said.append(line)
                if line.strip().startswith("plc"):
                    break
        assert (cell / "cell.toml").exists(), "".join(said)
        with open_mailbox(cell) as mailbox:
            mailbox.post_order("wax-robot-base", 1, order_id="A")
        run = await asyncio.create_subprocess_exec(
            *CELLCTL, "--cell", str(cell), "run", "--no-live",
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL,
        )  # fmt: skip
        await until(lambda: (cell / JOURNAL_FILE).exists(), "the journal", 60)
        with Journal(cell / JOURNAL_FILE) as journal:

            def alarms_on_cnc1() -> list[object]:
                return [a for a in journal.alarms() if a.machine == "cnc1"]

            (alarm,) = await until(alarms_on_cnc1, "an alarm on cnc1", 120)
            assert re.search(r"needs inspection: .* still running", alarm.text), alarm.text
            (held,) = journal.parts(statuses=["held"])
            assert held.location == "cnc1", held
            cuts = [s for s in journal.steps() if s.kind == "machine" and s.machine == "cnc1"]
            assert [s.state for s in cuts] == ["failed"], cuts
    finally:
        for process in (run, emulate):
            if process is not None and process.returncode is None:
                process.send_signal(signal.SIGINT)
        for process in (run, emulate):
            if process is not None:
                try:
                    async with asyncio.timeout(30):
                        await process.wait()
                except TimeoutError:
                    process.kill()
                    await process.wait()
