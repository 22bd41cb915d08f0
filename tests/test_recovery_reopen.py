"""A mill's link reopened after a drop: once, and not every round while its device server
refuses (ser2net takes a connection and closes it at once for a moment after a drop, "Port
already in use"). The example cell on virtual time (docs/clock.md): the server's refusals are
counted over a stretch of the cell's own time, against the pauses docs/cell.md states.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.cell.recovery import REOPEN_WAIT_MAX
from cellctl.clock import current_clock
from cellctl.testing.rig import CellRig

#: How long the device server refuses, s of the cell's time.
REFUSING = 20.0


@pytest.mark.virtual
async def test_a_refusing_device_server_is_asked_again_after_growing_pauses(
    tmp_path: Path,
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 1, "A")
        # Each refused reopen fails cnc2's setup: not out of service for it within the test.
        controller = await rig.start_controller(fail_limit=1000)
        await rig.wait_for(rig.all_done, "order A done", timeout=600)
        clock = current_clock()
        poll = controller.options.poll_period
        async with rig.connections_dropped("cnc2") as taken:
            start = clock.monotonic()
            await rig.wait_for(
                lambda: clock.monotonic() - start >= REFUSING,
                f"{REFUSING:g} s of refusals",
                timeout=REFUSING + 10,
            )
            refused = len(taken)
        # Tried again (at once, then after a poll period, each pause twice the last up to
        # REOPEN_WAIT_MAX): not once a round (a round every poll period at the least).
        pauses, wait, due = 0, poll, 0.0
        while due <= REFUSING:
            pauses, due, wait = pauses + 1, due + wait, min(2 * wait, REOPEN_WAIT_MAX)
        assert 2 <= refused <= pauses + 1, (refused, [round(t - start, 2) for t in taken])
        assert refused < REFUSING / poll / 2
        # The emulator back on the line: reopened once, set up once, back in the plan.
        events = len(controller.events)
        await rig.wait_for(
            lambda: controller.recovery.usable("cnc2"), "cnc2 back in the plan", timeout=60
        )
        rig.post("wax-robot-base", 1, "B")
        await rig.wait_for(rig.all_done, "order B done", timeout=600)
        texts = [e.text for e in controller.events[events:]]
        assert texts.count("cnc2: link reopened") == 1, texts
        assert texts.count("cnc2: initialized with cnc2_setup.dyn") == 1, texts
        assert rig.cut_twice() == {}
        await rig.stop_controller()
