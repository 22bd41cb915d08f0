"""A controller aborted (a second Ctrl-C, the service stopped hard) holds the parts in flight
for the operator, and their notes say so, not "emergency stop" (there was none)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
from pathlib import Path

from cellctl.cell.journal import JOURNAL_FILE, Journal
from cellctl.mailbox import open_mailbox
from cellctl.service.client import attach
from cellctl.testing.rig import CellRig
from tests.conftest import CELLCTL, until


async def test_an_aborted_controller_holds_its_parts_naming_the_abort(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        controller = await rig.start_controller()
        rig.post("wax-robot-base", 1, "A1")
        await rig.wait_for(lambda: rig.open_steps("machine"), "a cut in flight", timeout=60)
        # What asyncio.run does on KeyboardInterrupt: every task cancelled.
        tasks = [*controller.steps_in_flight(), rig._run_task]
        for task in tasks:
            assert task is not None
            task.cancel()
        for task in tasks:
            assert task is not None
            with contextlib.suppress(asyncio.CancelledError):
                async with asyncio.timeout(30):
                    await task
        rig._run_task = None
        [held] = rig.held_parts()
        # Cut short mid-cut, or stopped before a byte of it went out: the abort either way.
        assert "the controller's abort" in (held.note or ""), held.note
        assert "emergency stop" not in (held.note or "")
        assert not rig.alarms("cell", "estop")  # no emergency stop was raised for it
        await controller.close()
        rig.controller = None


async def test_an_abort_with_a_client_attached_says_interrupted_and_no_traceback(
    tmp_path: Path,
) -> None:
    """`cellctl run` aborted by a second Ctrl-C while a console (an API session) is attached:
    "interrupted" and 130, not an ASGI application's traceback for the session cut off."""
    cell = tmp_path / "cell"
    env = {**os.environ, "NO_COLOR": "1"}
    quiet = asyncio.subprocess.DEVNULL
    procs = [
        await asyncio.create_subprocess_exec(
            *CELLCTL, "--cell", str(cell), "emulate", "cell", "--time-scale", "100",
            stdout=quiet, stderr=quiet, env=env,
        )
    ]  # fmt: skip
    try:
        await until(lambda: (cell / "cell.toml").exists(), "the emulated cell's cell.toml", 60)
        with open_mailbox(cell) as mailbox:
            mailbox.post_order("wax-robot-base", 1, order_id="A")
        run = await asyncio.create_subprocess_exec(
            *CELLCTL, "--cell", str(cell), "run", "--no-live",
            stdout=quiet, stderr=asyncio.subprocess.PIPE, env=env,
        )  # fmt: skip
        procs.append(run)
        await until(lambda: (cell / "api.sock").exists(), "the controller's API socket", 60)
        client = await attach(cell)
        try:
            with Journal(cell / JOURNAL_FILE) as journal:
                # A cut in flight (seconds long): the first Ctrl-C waits for it, the second
                # aborts.
                def cutting() -> bool:
                    return any(s.kind == "machine" for s in journal.open_steps())

                await until(cutting, "a cut in flight", 60)
            run.send_signal(signal.SIGINT)
            await asyncio.sleep(0.2)
            run.send_signal(signal.SIGINT)
            assert run.stderr is not None
            async with asyncio.timeout(60):
                said = (await run.stderr.read()).decode()
                code = await run.wait()
        finally:
            with contextlib.suppress(Exception):
                await client.close()
        assert code == 130, said
        assert "interrupted" in said and "Traceback" not in said, said
        assert "Exception in ASGI application" not in said, said
    finally:
        for proc in reversed(procs):
            if proc.returncode is None:
                proc.terminate()
                await proc.wait()
