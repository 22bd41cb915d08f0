"""A cut run by hand through a running cell's API (a mill out of automatic service, then
``mill.download``) shows on the status as the controller's own cuts do: the manual step's
program and start, and its progress (bytes, blocks, phase, the estimate), on every surface
(another console's board too), until the call ends, however it ends."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import pytest

from cellctl.errors import CellctlError
from cellctl.kinds import Condition
from cellctl.service.access import AttachedCell
from cellctl.service.client import CellClient, attach
from cellctl.service.server import ApiServer
from cellctl.service.status import CellStatus
from cellctl.testing.rig import CellRig
from cellctl.ui.console.app import ConsoleApp
from tests.test_console import SIZE, rig, screen_text  # noqa: F401 (the fixture)

#: cnc2's own program of the example cell (one block).
PROGRAM = "toy_mill_table_finish_cnc2.dyn"


@pytest.fixture
async def cell(rig: CellRig) -> AsyncIterator[tuple[CellRig, AttachedCell, CellClient]]:  # noqa: F811
    """A controller runs the cell, its API on the cell's socket; cnc2 out of service."""
    controller = await rig.start_controller()
    access = AttachedCell(controller)
    server = ApiServer(access, rig.directory)
    await server.start()
    client = await attach(rig.directory)
    try:
        # Set up by the controller (its reference zero set: it takes a program), then out.
        await rig.wait_for(
            lambda: access.status().machines["cnc2"].condition is Condition.IDLE, "cnc2 idle"
        )
        await client.call("machines.out_of_service", {"machine": "cnc2", "reason": "by hand"})
        yield rig, access, client
    finally:
        await client.close()
        await server.close()


def download(cnc: CellRig, client: CellClient) -> asyncio.Task[Any]:
    text = (cnc.directory / "programs" / PROGRAM).read_text()
    params = {"machine": "cnc2", "program": PROGRAM, "text": text}
    return asyncio.create_task(client.call("mill.download", params))


async def test_a_manual_download_shows_its_step_and_progress_on_the_status(
    cell: tuple[CellRig, AttachedCell, CellClient],
) -> None:
    cnc, access, client = cell
    call = download(cnc, client)

    def sending() -> CellStatus | None:
        assert not call.done() or call.exception() is None, call.exception()
        status = access.status()
        m = status.machines["cnc2"]
        return status if m.progress is not None and m.progress.done > 0 else None

    status = await cnc.wait_for(sending, "cnc2's manual download in its progress", 60)
    m = status.machines["cnc2"]
    assert m.step is not None and m.step.what.value == "manual"
    assert m.step.program == PROGRAM and m.step.started is not None
    assert m.step.started <= status.cell.time
    p = m.progress
    assert p is not None and p.unit == "bytes" and 0 < p.done <= p.total
    assert p.program == PROGRAM and p.blocks and p.block
    assert p.phase in ("sending", "machining", "waiting", "done")
    # The HTTP/API reading says the same (what the dashboard reads).
    over_api = await client.call("cell.status")
    assert over_api["machines"]["cnc2"]["step"]["program"] == PROGRAM
    async with asyncio.timeout(120):
        result = await call
    assert "Download was correct" in result["message"]
    after = access.status().machines["cnc2"]
    assert after.progress is None and after.step is None
    assert (await client.call("cell.status"))["machines"]["cnc2"]["progress"] is None


async def test_a_manual_download_that_fails_clears_its_progress(
    cell: tuple[CellRig, AttachedCell, CellClient],
) -> None:
    cnc, access, client = cell
    cnc.switch_on("cnc2:drop=20")  # the line drops 20 lines into the block
    call = download(cnc, client)
    seen = await cnc.wait_for(
        lambda: access.status().machines["cnc2"].progress or call.done(),
        "cnc2's progress, or the call's end",
        60,
    )
    assert seen is True or seen.unit == "bytes"
    with pytest.raises(CellctlError):
        async with asyncio.timeout(120):
            await call
    m = access.status().machines["cnc2"]
    assert m.step is None and m.progress is None
    assert (await client.call("cell.status"))["machines"]["cnc2"]["progress"] is None


async def test_another_console_shows_the_manual_cut_on_its_board(
    cell: tuple[CellRig, AttachedCell, CellClient],
) -> None:
    cnc, _access, client = cell
    watcher = await attach(cnc.directory)
    app = ConsoleApp(cnc.directory, watcher, traffic_period=0.1)
    try:
        async with app.run_test(size=SIZE) as pilot:
            await cnc.wait_for(lambda: "attached to cellctl run" in screen_text(app), "the console")
            call = download(cnc, client)

            def bar_on_board() -> str | None:
                assert not call.done() or call.exception() is None, call.exception()
                lines = screen_text(app).splitlines()
                rows = [i for i, line in enumerate(lines) if "cnc2 " in line]
                below = [lines[i + 1] for i in rows if i + 1 < len(lines)]
                shown = [line for line in below if "░" in line or "█" in line]
                return shown[0] if shown else None

            async def looked() -> str | None:
                await pilot.pause(0.02)
                return bar_on_board()

            loop = asyncio.get_running_loop()
            deadline = loop.time() + 60
            line = None
            while line is None:
                assert loop.time() < deadline, screen_text(app)
                line = await looked()
            # At 80x24 the board's line keeps its figures: the block and the time left.
            assert "b1/1" in line and "left" in line, line
            async with asyncio.timeout(120):
                await call
            while bar_on_board() is not None:
                assert loop.time() < deadline + 120, screen_text(app)
                await pilot.pause(0.05)
            await pilot.press("q")
    finally:
        await watcher.close()
