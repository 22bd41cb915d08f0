"""Closing a cell ends everything it started: the controller's steps in flight and its
recoveries, and the emulated machines' own work (a program executing), mid-cut too. A process
that runs cells one after another (a notebook, the tests, a service playing plans) keeps
nothing running.

The cut closed mid-way runs on real links (ptys, RFC 2217): a step left running there failed
as the machines' links closed under it, and its failure started a recovery that polled on."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from cellctl.testing.rig import CellRig


def _left() -> list[str]:
    me = asyncio.current_task()
    return sorted(repr(t.get_coro()) for t in asyncio.all_tasks() if t is not me)


async def test_a_cell_closed_mid_cut_leaves_no_task_running(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        rig.post("wax-toy-mill-table", 2, "A")
        # The emulated mill runs its block on its own, the controller's step waiting on it.
        await rig.wait_for(
            lambda: rig.open_steps("machine") and any(m.executing for m in rig.cell.mills.values()),
            "a cut in flight",
            timeout=60,
        )
    assert _left() == []


def _recovering() -> bool:
    return any("Recovery._recover" in repr(t.get_coro()) for t in asyncio.all_tasks())


@pytest.mark.virtual
async def test_a_cell_closed_while_a_mill_recovers_leaves_no_task_running(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        rig.cell.mills["cnc1"].set_fault("drop", "2")  # its link drops in the first cut
        rig.post("wax-toy-mill-table", 1, "A")
        await rig.wait_for(_recovering, "cnc1 recovering from its dropped link", timeout=3600)
    assert _left() == []
