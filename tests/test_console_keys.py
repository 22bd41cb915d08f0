"""The console's keys and screen edges, driven with Textual's Pilot at 80x24 against the
emulated cell (standalone: the console holds the links): Ctrl-C quits as ``q`` does, the
robot's ``e. IO SET`` asks what it drives, and the header keeps the console's state whole
in the terminal's width.
"""

from __future__ import annotations

from cellctl.testing.rig import CellRig
from cellctl.ui.console.app import ConsoleApp
from cellctl.ui.console.widgets import header_text
from tests.test_console import SIZE, rig, standalone_client, type_text, wait_text

__all__ = ["rig"]  # the fixture, used by name


async def test_standalone_robot_io_set_asks_its_input(rig: CellRig) -> None:
    """The robot menu's ``e. IO SET`` asks which input and on or off (refused in the
    function's words before anything is sent), drives it, and DI/DO shows it."""
    app = ConsoleApp(rig.directory, standalone_client(rig), traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("1")
        await wait_text(pilot, "e. IO SET")
        await pilot.press("e")
        await wait_text(pilot, "Input (1-16):", "On (off if not ticked)")
        await type_text(pilot, "17")
        await pilot.press("enter")
        await wait_text(pilot, "input must be 1 to 16, not 17")
        await type_text(pilot, "3")  # replaces the refused 17
        await pilot.press("tab", "space")  # On ticked
        await pilot.click("#ok")
        await wait_text(pilot, "robot: IO SET: input 3 on")
        await pilot.press("b")
        await wait_text(pilot, "robot: DI/DO: DI ..1")
        await pilot.press("q")


async def test_ctrl_c_quits_as_q_does(rig: CellRig) -> None:
    """Ctrl-C quits the console as ``q`` does (Textual's own would only say how to quit),
    from a menu and from a dialog too, and the links it held are released: another console
    then uses the robot."""
    for keys in (["ctrl+c"], ["2", "ctrl+c"]):
        app = ConsoleApp(rig.directory, standalone_client(rig), traffic_period=0.1)
        async with app.run_test(size=SIZE) as pilot:
            await wait_text(pilot, "MAIN MENU")
            await pilot.press("1", "4")  # the robot's link opened and held
            await wait_text(pilot, "robot: STATUS: robot state")
            await pilot.press(*keys)
            await rig.wait_for(lambda a=app: not a.is_running, f"{keys}: the console quit", 15)
    app = ConsoleApp(rig.directory, standalone_client(rig), traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("1", "4")
        await wait_text(pilot, "robot: STATUS: robot state")
        await pilot.press("q")


def test_the_header_says_the_state_whole_in_the_terminals_width() -> None:
    """The console's state whole; the directory cut at its start to fit beside it, or on
    the next line when the state leaves too little room."""
    deep = "/srv/cells/" + "x" * 80 + "/lab"
    line = header_text("attached to cellctl run (pid 42)", "cell", deep, 78)
    assert len(line) == 78 and line.startswith("attached to cellctl run (pid 42)  cell: …")
    assert line.endswith("xx/lab")
    state = "DISCONNECTED: controller's API closed; attaching again when it runs (q quits)"
    first, second = header_text(state, "cell", deep, 78).split("\n")
    assert first == state and second.startswith("cell: …") and len(second) == 78
    assert header_text("standalone", "cell", "mycell", 78) == "standalone  cell: mycell"
