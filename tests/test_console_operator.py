"""The console as an operator found it (issue 19, finding 11), driven with Textual's Pilot at
80x24 against the emulated cell: the robot's DOWNLOAD takes an AML source (compiled on the
way), STATUS says the state once, the traffic pane shows the operator's own command, CELL ->
ORDERS follows the orders while open, and a standalone mill set up by INITIALIZE is not shown
as "Uninitialized".

Assertions are on the screen, the emulators and the cell's own records.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.service.client import CellClient
from cellctl.service.functions import function
from cellctl.testing.rig import CellRig
from cellctl.ui.console.app import ConsoleApp
from cellctl.ui.console.session import ConsoleMachine, check_params
from tests.test_console import (
    EXAMPLES,
    SIZE,
    attached,
    fill,
    rig,
    screen_text,
    standalone_client,
    wait_text,
)

__all__ = ["attached", "rig"]  # the fixtures, used by name


@pytest.mark.virtual
async def test_download_offers_aml_and_compiles_it_on_the_way(rig: CellRig) -> None:
    client = standalone_client(rig)
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("1")
        await wait_text(pilot, "ROBOT (robot)")
        await pilot.press("1")
        await wait_text(pilot, "robot: INITIALIZE: Initializing was correct")
        await pilot.press("2")
        await wait_text(pilot, "Partition (1-5):")
        pilot.app.screen.query_one("#tree").focus()
        await pilot.press("down", "down", "enter")  # open robot/ (after programs/)
        await wait_text(pilot, "cnc1_to_cnc2.aml")
        await fill(pilot, "#partition", "2")
        await fill(pilot, "#program", "robot/cnc1_to_cnc2.aml")
        await pilot.click("#ok")
        await wait_text(pilot, "robot: DOWNLOAD: Download was correct", timeout=30)
        # The compiled program is in partition 2 under the name the compiler gives it.
        assert rig.cell.robot.partitions[2] is not None
        await pilot.press("4")
        shown = await wait_text(pilot, "robot: STATUS: robot state 1 (Initialized")
        # STATUS says the robot's state once (in the result, below the menu and the board).
        result = [line for line in shown.splitlines() if "│" not in line]
        assert sum("robot state" in line for line in result) == 1, shown
        await pilot.press("q")


@pytest.mark.virtual
async def test_a_broken_aml_source_is_refused_in_the_dialog(rig: CellRig) -> None:
    (rig.directory / "broken.aml").write_text("THIS IS NOT AML;\n")
    client = standalone_client(rig)
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("1", "2")
        await wait_text(pilot, "Partition (1-5):")
        await fill(pilot, "#partition", "1")
        await fill(pilot, "#program", "broken.aml")
        await pilot.press("enter")
        shown = await wait_text(pilot, "broken.aml")
        assert "Partition (1-5):" in shown  # still the dialog: nothing was sent
        rows = await client.call("traffic.tail", {"machine": "robot", "limit": 10})
        assert rows == []
        await pilot.press("escape", "q")


@pytest.mark.virtual
async def test_the_traffic_pane_shows_the_operators_own_command(rig: CellRig) -> None:
    client = standalone_client(rig)
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("1")
        await wait_text(pilot, "ROBOT (robot)")
        given = current_clock().now()  # the traffic's stamps: the cell's clock
        await pilot.press("4")
        await wait_text(pilot, "robot: STATUS: robot state")
        rows = await client.call("traffic.tail", {"machine": "robot", "limit": 2000})
        sent = [r for r in rows if r["dir"] == ">>" and r["time"] >= given]
        assert sent and len(rows) > 4  # the answer alone fills a 4-row pane
        # The command's first bytes on top of the pane, marked as the operator's.
        await wait_text(pilot, f">>* {sent[0]['hex']}")
        await pilot.press("q")


async def test_cell_orders_follows_the_orders_while_open(
    rig: CellRig, attached: CellClient
) -> None:
    app = ConsoleApp(rig.directory, attached, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "attached to cellctl run")
        await pilot.press("c")
        await wait_text(pilot, "1. ORDERS")
        await pilot.press("6")  # PAUSE: the order stays where it is put
        await wait_text(pilot, "6. RESUME")
        rig.post("wax-robot-base", 1, "L1")
        await pilot.press("1")
        await wait_text(pilot, "ORDERS (live)", "L1 wax-robot-base x1")
        # While the list is open: a new order appears, and L1 moves on when resumed.
        rig.post("wax-robot-base", 1, "L2")
        await wait_text(pilot, "ORDERS (live)", "L2 wax-robot-base x1")
        await attached.call("cell.resume", {})
        await rig.wait_for(lambda: rig.order_state("L1") == "done", "L1 done", timeout=60)
        await wait_text(pilot, "ORDERS (live)", "L1 wax-robot-base x1 p0 done", timeout=15)
        await pilot.press("escape", "escape", "q")


@pytest.mark.virtual
async def test_standalone_mill_after_initialize_is_not_uninitialized(rig: CellRig) -> None:
    client = standalone_client(rig)
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("2", "1")
        await wait_text(pilot, "Force (initialize again)")
        await pilot.press("enter")
        await wait_text(pilot, "cnc1: INITIALIZE: Initializing was correct", timeout=20)
        # The emulated operator sets the reference zero and presses NEXT: the board follows
        # without a STATUS asked for.
        shown = await wait_text(pilot, "cnc1   OUT    Initialized", timeout=30)
        board = [line for line in shown.splitlines() if "cnc1 " in line]
        assert board and not any("Uninitialized" in line for line in board), shown
        assert "cnc1: STATUS" not in screen_text(app)
        await pilot.press("q")


AML = (EXAMPLES / "robot" / "conveyor_to_cnc1.aml").read_text()


@settings(max_examples=150, deadline=None)
@given(
    text=st.one_of(
        st.text(max_size=400),
        st.integers(0, len(AML)).map(lambda n: AML[:n]),  # a real source, cut anywhere
    ),
    partition=st.sampled_from(["1", "5", "6", ""]),
)
def test_an_aml_source_gives_parameters_or_a_usage_error(text: str, partition: str) -> None:
    """Whatever an .aml file holds, DOWNLOAD's check compiles it into a program the function
    takes, or says what is wrong (a UsageError): nothing else comes out."""
    fn = function("robot", "download")
    with tempfile.TemporaryDirectory() as folder:
        directory = Path(folder)
        (directory / "load.aml").write_text(text, encoding="utf-8")
        raw = {"partition": partition, "program": "load.aml"}
        try:
            params = check_params(ConsoleMachine("m", "robot", "ROBOT"), fn, raw, directory)
        except UsageError as e:
            assert str(e)
        else:
            assert params["program"] == "load.rec"
            fn.check(params)  # accepted as it will be sent
