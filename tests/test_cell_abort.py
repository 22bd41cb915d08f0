"""A controller aborted (a second Ctrl-C, the service stopped hard) holds the parts in flight
for the operator, and their notes say so, not "emergency stop" (there was none)."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

from cellctl.testing.rig import CellRig


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
