"""Closing a cell ends everything it started: the controller's recoveries and the emulated
machines' own work (a program executing) end with it, mid-cut too. A process that runs cells
one after another (a notebook, the tests, a service playing plans) keeps nothing running."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from cellctl.testing.rig import CellRig


def _left() -> list[str]:
    me = asyncio.current_task()
    return sorted(repr(t.get_coro()) for t in asyncio.all_tasks() if t is not me)


@pytest.mark.virtual
async def test_a_cell_closed_mid_cut_leaves_no_task_running(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        rig.post("wax-toy-mill-table", 2, "A")
        await rig.wait_for(lambda: rig.open_steps("machine"), "a cut in flight", timeout=3600)
        mill = rig.cell.mills[rig.open_steps("machine")[0].machine]
        assert mill.executing  # the emulated mill runs its block on its own
    assert _left() == []
