"""A cut's progress and time left come from the program's estimate (its line time and its
toolpath's cut time), corrected by the mill's own reports, on the typed status every surface
reads: no "100 %" and no "0 s left" for the whole cut (issue 19, finding 4)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from cellctl.kinds.dyna2400.driver import Progress
from cellctl.kinds.dyna2400.dynalan import ValidationContext, parse_program, validate
from cellctl.kinds.families import RUNNING_AT_MOST, estimated_done
from cellctl.service.access import AttachedCell
from cellctl.service.status import ProgressInfo
from cellctl.testing.rig import CellRig
from tests.test_mill_driver import LONG, Cell, cell  # noqa: F401 (the fixture)


def test_the_estimate_moves_with_the_clock_up_to_the_machines_report() -> None:
    raw = {"estimate_s": 10.0, "estimate_done_s": 2.0, "estimate_cap_s": 6.0, "at": 100.0}
    assert estimated_done(raw, 103.0) == 2.0  # not running: what was reported
    raw["running"] = True
    assert estimated_done(raw, 101.0) == 3.0
    assert estimated_done(raw, 200.0) == 6.0  # the block's end: the machine says the rest
    raw["estimate_cap_s"] = 10.0
    assert estimated_done(raw, 500.0) == RUNNING_AT_MOST * 10.0  # never 100 % while it cuts
    assert estimated_done({"estimate_s": 0.0}, 1.0) is None


@pytest.mark.parametrize("cell", ["rfc2217"], indirect=True)
async def test_the_mills_reports_carry_the_programs_estimate(cell: Cell) -> None:  # noqa: F811
    mill = await cell.ready_mill(time_scale=20000.0)
    cell.emulator.time_scale = 20000.0
    seen: list[Progress] = []
    async with mill:
        await mill.download(LONG, progress=seen.append)
        wire = mill.link.settings.wire_time
    program = parse_program(LONG.read_text(), name=LONG.name)
    found = validate(program, ValidationContext(config=mill.config.machine()))
    assert found.toolpath is not None and found.blocks is not None
    cut = sum(found.toolpath.block_seconds) / 20000.0
    line = sum(wire(len(b.wire()) + 1) for b in found.blocks)
    assert seen[0].estimate_s == pytest.approx(cut + line)
    # Each block is taken, then cut: its report while cutting runs up to that block's end.
    cutting = [p for p in seen if p.phase == "machining"]
    assert [p.block for p in cutting] == [1, 2, 3]
    assert all(p.running and p.estimate_done_s < p.estimate_cap_s for p in cutting)
    assert [p.estimate_cap_s for p in cutting] == sorted(p.estimate_cap_s for p in cutting)
    assert cutting[-1].estimate_cap_s == pytest.approx(seen[0].estimate_s)
    assert seen[-1].phase == "done" and seen[-1].estimate_done_s == seen[-1].estimate_s


@pytest.mark.virtual
async def test_a_cut_shows_progress_and_time_left_on_the_status(tmp_path: Path) -> None:
    async with CellRig(tmp_path) as rig:
        rig.post("wax-robot-base", 1, "P")
        controller = await rig.start_controller()
        access = AttachedCell(controller)
        cuts: dict[tuple[str, str], list[ProgressInfo]] = {}
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 60
        while rig.order_state("P") != "done":
            assert loop.time() < deadline, rig.describe()
            rig.check_running()
            for m in access.status().machines.values():
                p = m.progress
                if m.family == "mill" and p is not None and p.phase == "machining":
                    cuts.setdefault((m.name, f"{p.program} {p.block}"), []).append(p)
            await asyncio.sleep(0.01)
        assert cuts, "no cut seen"
        for samples in cuts.values():
            assert all(p.estimate_s and 0 < p.fraction < 1 for p in samples)
            assert all(p.time_left_s is not None for p in samples)
            # Not "0 s left" for the whole cut: it starts from the cut's estimate.
            assert samples[0].time_left_s and samples[0].time_left_s > 0
            fractions = [p.fraction for p in samples]
            assert fractions == sorted(fractions)  # it moves on with the cut, never back
            lefts = [p.time_left_s for p in samples]
            assert lefts == sorted(lefts, reverse=True)
        # A long cut seen more than once moved between two looks.
        longest = max(cuts.values(), key=len)
        assert len(longest) > 2 and longest[-1].fraction > longest[0].fraction
