"""The operator console (``cellctl console``) driven with Textual's Pilot at 80x24, against
the emulated cell: every menu path, standalone (the console holds the links) and attached
(everything through a running controller's API).

Assertions are on what the screen shows (the source's messages) and on the cell (journal,
emulators, traffic), never on the console's internals.
"""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import tempfile
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from textual.pilot import Pilot

from cellctl.cell.owner import acquire_controller_lock, controller_holder
from cellctl.errors import UsageError
from cellctl.kinds.dyna2400.emulator import LinkMode
from cellctl.kinds.ibm7545.aml import compile_source
from cellctl.service import publish as publish_module
from cellctl.service.access import AttachedCell, LocalCell
from cellctl.service.client import CellClient, StandaloneCell, attach
from cellctl.service.functions import function
from cellctl.service.server import ApiServer
from cellctl.testing.rig import CellRig
from cellctl.ui.console.app import ConsoleApp
from cellctl.ui.console.session import ConsoleMachine, cell_refs, check_params

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
SIZE = (80, 24)


def screen_text(app: ConsoleApp) -> str:
    """What the terminal shows now (the top screen, dialogs included), as plain text."""
    return "\n".join(strip.text for strip in app.screen._compositor.render_strips())


async def wait_text(pilot: Pilot[Any], *texts: str, timeout: float = 15.0) -> str:
    """Wait until every one of ``texts`` is on the screen; fail with the screen otherwise."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        await pilot.pause(0.02)
        shown = screen_text(pilot.app)  # type: ignore[arg-type]
        if all(t in shown for t in texts):
            return shown
        if loop.time() > deadline:
            raise AssertionError(f"not on screen: {texts}\n{shown}")


async def type_text(pilot: Pilot[Any], text: str) -> None:
    await pilot.press(*[{" ": "space", ".": "full_stop", "/": "slash"}.get(c, c) for c in text])


async def fill(pilot: Pilot[Any], selector: str, text: str) -> None:
    """Replace the text of a dialog's input."""
    field = pilot.app.screen.query_one(selector)
    field.value = text  # type: ignore[attr-defined]
    await pilot.pause()


#: A short milling program (a few moves: the cut takes little machine time).
SHORT_MILLING = """\
000 ; CONSOLE TEST - A SHORT CUT
001 TOOL 01
002 TD = .500
003 SP= 4000 RPM
004 SPINDLE ON
005 FR XY = 12.0
006 FR Z = 4.0
007 GOf X 1.000
008   Y 1.125
009 GO Z -.050
010 GR X 1.500
011 Z>C
012 SPINDLE OFF
013 SKIP TO 900
900
"""


def write_robot_program(directory: Path, name: str = "load1.rec") -> Path:
    """A compiled examples/robot program in the cell directory (what DOWNLOAD sends)."""
    source = (EXAMPLES / "robot" / "conveyor_to_cnc1.aml").read_text()
    path = directory / name
    path.write_text(compile_source(source, "LOAD1", 1).to_text())
    return path


async def traffic_rows(client: CellClient, machine: str) -> int:
    rows = await client.call("traffic.tail", {"machine": machine, "limit": 2000})
    return len(rows)


#: Deadlines for a loaded test box. The console renders in the same loop as the controller,
#: its drivers and the emulators, and a box running the suite (or other work) beside these
#: tests can hold that loop up for seconds: the fast deadlines (a second for a PLC request or
#: a look at an idle machine, two for the robot's reply, a second and a half over a mill's
#: block, the emulated robot's second for the host) would tell a machine that answered late
#: as not answering or stuck, and raise an alarm these tests do not expect. They are about
#: the console, not about finding a silent machine (tests/test_cell_faults.py is, on virtual
#: time, where load cannot make a read late).
LOADED_BOX_S = 10.0
LOADED_CELL_OPTIONS = {
    "read_limit": LOADED_BOX_S,
    "transfer_timeout": 60.0,
    "interlock_timeout": LOADED_BOX_S,
    "pallet_timeout": LOADED_BOX_S,
}
LOADED_MILL_OPTIONS = {"setup_timeout": LOADED_BOX_S, "block_extra": LOADED_BOX_S}


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[CellRig]:
    async with CellRig(
        tmp_path / "cell",
        cell_options=LOADED_CELL_OPTIONS,
        mill_options=LOADED_MILL_OPTIONS,
        plc_options={"timeout": LOADED_BOX_S},
    ) as rig:
        # The emulated robot's own wait for the host (a second of wall time at this scale).
        rig.cell.robot.host_timeout_s = LOADED_BOX_S * rig.cell.robot.time_scale
        toml = rig.directory / "cell.toml"
        text = toml.read_text()
        text += f"\n[machines.robot.options]\nreply_timeout = {LOADED_BOX_S}\n"
        toml.write_text(text)
        yield rig


def standalone_client(rig: CellRig) -> StandaloneCell:
    return StandaloneCell(LocalCell(rig.directory, cell_refs(rig.directory)))


@pytest.fixture
async def attached(rig: CellRig) -> AsyncIterator[CellClient]:
    """A controller runs the cell in this process, its API on the cell's socket."""
    await rig.start_controller()
    assert rig.controller is not None
    server = ApiServer(AttachedCell(rig.controller), rig.directory)
    await server.start()
    client = await attach(rig.directory)
    try:
        yield client
    finally:
        await client.close()
        await server.close()


# -- standalone --------------------------------------------------------------------------------


@pytest.mark.virtual
async def test_standalone_robot_menu_every_function(rig: CellRig) -> None:
    write_robot_program(rig.directory)
    bad = rig.directory / "bad.rec"
    bad.write_text("N1LOAD1   99\nthis is not a record\n")
    client = standalone_client(rig)
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        shown = await wait_text(pilot, "standalone: links held by this console")
        # The source's main menu numbers; the cell's own menu has a letter.
        for entry in ("1. ROBOT", "2. NC MACHINE #1", "3. NC MACHINE #2", "4. EXIT", "c. CELL"):
            assert entry in shown
        assert "5." not in shown
        await pilot.press("1")
        shown = await wait_text(pilot, "ROBOT (robot)", "7. EXIT")
        for entry in ("1. INITIALIZE", "2. DOWNLOAD", "3. GO", "4. STATUS", "5. STOP"):
            assert entry in shown
        assert "6. HALT" in shown and "d. RETURN HOME" in shown
        await pilot.press("1")
        await wait_text(pilot, "robot: INITIALIZE: Initializing was correct")

        # Bad input is refused in the dialog, with nothing sent.
        before = await traffic_rows(client, "robot")
        await pilot.press("2")
        await wait_text(pilot, "Partition (1-5):")
        await fill(pilot, "#partition", "6")
        await fill(pilot, "#program", "load1.rec")
        await pilot.press("enter")
        await wait_text(pilot, "partition must be 1 to 5, not 6")
        await fill(pilot, "#partition", "3")
        await fill(pilot, "#program", "bad.rec")
        await pilot.press("enter")
        await wait_text(pilot, "bad.rec, line 1")
        await fill(pilot, "#program", "missing.rec")
        await pilot.press("enter")
        await wait_text(pilot, "missing.rec: could not open file: no such file")
        assert await traffic_rows(client, "robot") == before
        # The picker: the cell directory's folders and .rec files (bad.rec, load1.rec).
        pilot.app.screen.query_one("#tree").focus()
        await wait_text(pilot, "load1.rec", "bad.rec")
        await pilot.press("down", "down", "down", "down", "enter")
        program = pilot.app.screen.query_one("#program")
        await rig.wait_for(lambda: program.value == "load1.rec", "load1.rec picked")  # type: ignore[attr-defined]
        await pilot.click("#ok")
        await wait_text(pilot, "robot: DOWNLOAD: Download was correct")
        assert rig.cell.robot.partitions[3] is not None

        await pilot.press("3")
        await wait_text(pilot, "Partition (1-5):")
        await type_text(pilot, "5")
        await pilot.press("enter")
        # Refused by the host's state, before a byte goes out: the source's code and words.
        await wait_text(pilot, "robot: GO: partition empty (code 3)")
        await pilot.press("3")
        await wait_text(pilot, "Partition (1-5):")
        await type_text(pilot, "3")
        await pilot.press("enter")
        await wait_text(pilot, "robot: GO: Started Cycle")
        await pilot.press("5")
        await wait_text(pilot, "robot: STOP:")
        await pilot.press("4")
        await wait_text(pilot, "robot: STATUS: robot state", "3 Full (LOAD1)", "5 Empty")
        await pilot.press("a")
        await wait_text(pilot, "Reject status")
        await pilot.press("b")
        await wait_text(pilot, "robot: DI/DO: DI ")
        await pilot.press("c")
        await wait_text(pilot, "Errors reset")
        await pilot.press("d")
        await wait_text(pilot, "robot: RETURN HOME: Home")
        await pilot.press("6")
        await wait_text(pilot, "robot: HALT: Halted")
        await wait_text(pilot, ">>", "<<")  # the traffic pane shows both ways
        await pilot.press("7")
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("q")
    assert app.return_code == 0
    # Quitting released the links: a new standalone client opens the robot at once.
    async with standalone_client(rig) as again:
        status = await again.call("robot.status", {"machine": "robot"})
        assert status["state_text"] == "Uninitialized"


@pytest.mark.virtual
async def test_standalone_mill_menu_every_function(rig: CellRig) -> None:
    (rig.directory / "short.dyn").write_text(SHORT_MILLING)
    toml = rig.directory / "cell.toml"  # a GO the mill does not take is told within 1.5 s
    toml.write_text(
        toml.read_text().replace("ready_wait = 1\n", "ready_wait = 1\naccept_timeout = 1.5\n")
    )
    broken = rig.directory / "broken.dyn"
    shutil.copy(EXAMPLES / "programs" / "broken" / "feed_too_fast.dyn", broken)
    client = standalone_client(rig)
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    mill = rig.cell.mills["cnc1"]
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("2")
        shown = await wait_text(pilot, "NC MACHINE #1 (cnc1)", "6. EXIT")
        for entry in ("1. INITIALIZE", "2. DOWNLOAD", "3. GO", "4. STATUS", "5. HALT"):
            assert entry in shown
        assert "a. PROGRAM LOAD" in shown and "b. UPLOAD" in shown
        assert "s. SERVICE (unavailable)" in shown
        await pilot.press("4")
        await wait_text(pilot, "cnc1: STATUS: state")
        # INITIALIZE offers the setup program cell.toml names.
        await pilot.press("1")
        await wait_text(pilot, "Force (initialize again)")
        assert pilot.app.screen.query_one("#program").value == "programs/cnc1_setup.dyn"  # type: ignore[attr-defined]
        await pilot.press("enter")
        await wait_text(pilot, "cnc1: INITIALIZE: Initializing was correct", timeout=20)
        # A malformed program: every error with file:line:column, nothing sent.
        before = await traffic_rows(client, "cnc1")
        await pilot.press("2")
        await wait_text(pilot, "Program file:")
        await fill(pilot, "#program", "broken.dyn")
        await pilot.press("enter")
        await wait_text(pilot, "broken.dyn:2:14: error [feed-range] line 001: feed rate 40")
        assert await traffic_rows(client, "cnc1") == before
        await fill(pilot, "#program", "short.dyn")
        await pilot.press("enter")
        await wait_text(pilot, "cnc1: DOWNLOAD: Download was correct", timeout=30)
        assert mill.runs  # the emulator cut it
        await rig.wait_for(lambda: not mill.executing, "the cut done")
        await pilot.press("5")
        await wait_text(pilot, "cnc1: HALT: Ending was correct")
        mill.select(LinkMode.PROGRAM_LOAD)  # the operator's panel: ready to load
        await pilot.press("a")
        await wait_text(pilot, "Program file:")
        await fill(pilot, "#program", "short.dyn")
        await pilot.press("enter")
        await wait_text(pilot, "cnc1: PROGRAM LOAD: Load was correct")
        await pilot.press("3")
        # The source's message, or the driver's reason when the start signal did not start it.
        await wait_text(pilot, "cnc1: GO: ", timeout=20)
        await pilot.press("escape")
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("0")
    assert app.return_code == 0


@pytest.mark.virtual
async def test_standalone_cell_menu(rig: CellRig) -> None:
    app = ConsoleApp(rig.directory, standalone_client(rig), traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("down", "down", "down", "down", "enter")  # the arrows work as keys
        shown = await wait_text(pilot, "1. ORDERS", "8. EXIT")
        assert "6. PAUSE (unavailable)" in shown
        assert "7. EMERGENCY STOP (unavailable)" in shown
        await pilot.press("7")
        await wait_text(pilot, "EMERGENCY STOP: unavailable: no controller runs on this cell")
        await pilot.press("2")
        await wait_text(pilot, "SUBMIT ORDER")
        await fill(pilot, "#part_type", "no-such-part")
        await pilot.press("enter")
        await wait_text(pilot, "unknown part type 'no-such-part'")
        await fill(pilot, "#part_type", "wax-robot-base")
        await fill(pilot, "#qty", "2")
        await fill(pilot, "#id", "S1")
        await pilot.press("enter")
        await wait_text(pilot, "order S1 posted")
        assert rig.order_state("S1") == "posted"
        await pilot.press("1")
        await wait_text(pilot, "S1 wax-robot-base x2")
        await pilot.press("enter")
        await wait_text(pilot, "Cancel order S1?")
        await pilot.press("y")
        await wait_text(pilot, "cancelled")
        assert rig.order_state("S1") == "cancelled"
        await pilot.press("4")
        await wait_text(pilot, "no open alarm")
        await pilot.press("8")
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("4")
    assert app.return_code == 0


async def test_an_update_that_comes_as_the_console_exits_is_dropped(rig: CellRig) -> None:
    """The console exiting another way than its quit (its terminal gone, a test's end)
    removes its widgets while the client may still push: an update then is dropped, not an
    error in the exit."""
    app = ConsoleApp(rig.directory, standalone_client(rig), traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await app.query_one("#header").remove()  # as the exit removes the widgets
        app._cell_changed({})  # what the client calls with a pushed update
        await pilot.pause()
        assert not app.query("#header")


async def test_an_update_that_comes_as_a_menu_goes_is_dropped(rig: CellRig) -> None:
    """The same in a machine's menu, which an update refreshes: its menu removed first."""
    app = ConsoleApp(rig.directory, standalone_client(rig), traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("1")
        await wait_text(pilot, "ROBOT (robot)")
        await app.query_one("#menu").remove()  # as the exit removes the widgets
        app._cell_changed({})  # what the client calls with a pushed update
        await pilot.pause()
        assert not app.query("#menu") and app.level == "robot"


# -- attached ----------------------------------------------------------------------------------


async def test_attached_cell_menu(rig: CellRig, attached: CellClient) -> None:
    app = ConsoleApp(rig.directory, attached, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "attached to cellctl run (pid")
        await pilot.press("c")
        await wait_text(pilot, "6. PAUSE", "7. EMERGENCY STOP")
        await pilot.press("6")
        await wait_text(pilot, "paused: steps in flight finish", "6. RESUME", "CELL PAUSED")
        assert rig.controller is not None and rig.controller.paused
        # An order, submitted from the console.
        await pilot.press("2")
        await wait_text(pilot, "SUBMIT ORDER")
        await fill(pilot, "#qty", "2")
        await fill(pilot, "#id", "C1")
        await pilot.press("enter")
        await wait_text(pilot, "order C1 posted")
        await rig.wait_for(lambda: len(rig.journal.parts(order_id="C1")) == 2, "C1's parts")
        first, second = rig.journal.parts(order_id="C1")
        rig.journal.hold_part(first.id, "looked damaged")
        rig.journal.move_part(second.id, "cnc2")  # where the arm left it
        rig.journal.hold_part(second.id, "looked damaged")
        # Held parts: release one, scrap the other (asked by the machine it may be in).
        await pilot.press("5")
        await wait_text(pilot, "HELD PARTS", f"{first.id} wax-robot-base")
        await pilot.press("enter")
        await wait_text(pilot, f"PART {first.id}", "2. RELEASE WITH REDO")
        await pilot.press("enter")
        await wait_text(pilot, f"part {first.id} released")
        await pilot.press("5")
        await wait_text(pilot, f"{second.id} wax-robot-base")
        await pilot.press("enter")
        await wait_text(pilot, "3. SCRAP")
        await pilot.press("down", "down", "enter")
        await wait_text(pilot, f"Scrap part {second.id}?", "cnc2", "take it out first")
        await pilot.press("y")
        await wait_text(pilot, f"part {second.id} scrapped")
        statuses = {p.id: p.status for p in rig.journal.parts(order_id="C1")}
        assert statuses == {first.id: "waiting", second.id: "scrapped"}
        [scrapped] = rig.reports("part-scrapped")
        assert scrapped.data["taken_out_of"] == ["cnc2"]
        # An alarm raised by a fault switch, cleared from the console.
        rig.cell.plc.set_fault("estop", None)
        alarm = (await rig.wait_for(lambda: rig.alarms("plc", "estop"), "estop alarm"))[0]
        rig.cell.plc.clear_fault("estop")
        await wait_text(pilot, "ALARMS 1 open, 1 UNACKED", "plc estop")
        # Acknowledged first: it stays open, no longer flagged unacknowledged.
        await pilot.press("4")
        await wait_text(pilot, f"{alarm.id} plc estop", "UNACKED")
        await pilot.press("enter")
        await wait_text(pilot, "1. ACKNOWLEDGE", "3. CLEAR")
        await pilot.press("enter")
        await wait_text(pilot, f"alarm {alarm.id} acknowledged")
        await rig.wait_for(lambda: rig.journal.get_alarm(alarm.id).acked is not None, "acked")
        assert rig.journal.get_alarm(alarm.id).state == "active"
        await pilot.press("4")
        await wait_text(pilot, f"{alarm.id} plc estop", "acked")
        await pilot.press("enter")
        await wait_text(pilot, "3. CLEAR")
        await pilot.press("3")  # its number picks it, as in the menus
        await pilot.press("y")
        await wait_text(pilot, f"alarm {alarm.id} cleared", "ALARMS 0 open")
        assert not rig.alarms()
        await pilot.press("6")
        await wait_text(pilot, "resumed", "6. PAUSE")
        await rig.wait_for(lambda: rig.order_state("C1") == "done", "C1 done", timeout=60)
        await wait_text(pilot, "C1 wax-robot-base x2 p0 done")
        # The emergency stop asks first, with the reason (Escape: no stop).
        await pilot.press("7")
        await wait_text(pilot, "EMERGENCY STOP: stop the robot", "Reason:")
        await pilot.press("escape")
        await wait_text(pilot, "no emergency stop")
        await pilot.press("7")
        await wait_text(pilot, "Reason:")
        await type_text(pilot, "smoke at cnc2")  # replaces the offered reason
        await pilot.press("enter")
        await wait_text(pilot, "emergency stop: smoke at cnc2")
        assert rig.controller.paused
        await pilot.press("escape", "q")
    assert app.return_code == 0


async def test_attached_cnc2_by_hand_while_the_cell_works(
    rig: CellRig, attached: CellClient
) -> None:
    app = ConsoleApp(rig.directory, attached, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "attached to cellctl run")
        await pilot.press("3")
        await wait_text(pilot, "NC MACHINE #2 (cnc2)", "s. OUT OF SERVICE")
        # A manual function on a machine in automatic service asks to take it out first.
        await pilot.press("5")
        await wait_text(pilot, "cnc2 is in automatic service")
        await pilot.press("n")
        await wait_text(pilot, "not run: it stays in automatic service")
        await pilot.press("s")
        await wait_text(pilot, "Take cnc2 out of automatic service?", "Reason:")
        await type_text(pilot, "spindle noise")
        await pilot.press("enter")
        await wait_text(pilot, "cnc2 out of automatic service", "s. RETURN TO SERVICE")
        # The board shows each machine's condition (the status' field), cnc2's reason below.
        await wait_text(pilot, "cnc2   OUT    ", "taken out by the operator", "cnc1   idle   ")
        assert rig.journal.machines_out_of_service()["cnc2"].endswith("spindle noise")
        rig.post("wax-robot-base", 1, "M1")
        await rig.wait_for(
            lambda: any(s.machine == "cnc1" and s.state == "finished" for s in rig.journal.steps()),
            "cnc1 cut while cnc2 is out",
            timeout=60,
        )
        await pilot.press("4")
        await wait_text(pilot, "cnc2: STATUS: state 2")
        await pilot.press("5")
        await wait_text(pilot, "cnc2: HALT: Ending was correct")
        mill = rig.cell.mills["cnc2"]
        mill.select(mill.auto_mode)  # the operator selects the link mode on the panel
        await pilot.press("1")
        await wait_text(pilot, "Force (initialize again)")
        await pilot.click("#force")
        await pilot.click("#ok")
        await wait_text(pilot, "cnc2: INITIALIZE: Initializing was correct", timeout=20)
        await pilot.press("s")
        await wait_text(pilot, "Return cnc2 to automatic service?")
        await pilot.press("y")
        await wait_text(pilot, "cnc2 back in automatic service", "s. OUT OF SERVICE", timeout=20)
        await wait_text(pilot, "cnc2   idle   ")
        await rig.wait_for(lambda: rig.order_state("M1") == "done", "M1 done", timeout=60)
        await wait_text(pilot, "M1 wax-robot-base x1 p0 done")
        assert not rig.alarms() and not rig.cut_twice(), rig.describe()
        await pilot.press("q")
    assert app.return_code == 0


def test_console_command_without_a_cell_is_one_line_and_an_exit_code(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from cellctl.ui.cli import main

    result = CliRunner().invoke(main, ["--cell", str(tmp_path / "nowhere"), "console"])
    assert result.exit_code == 2
    assert "error: no cell in" in result.output and "Traceback" not in result.output


async def test_attached_robot_by_hand_after_its_step_in_flight(
    rig: CellRig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A function by hand on the robot waits for its transfer in flight, as the controller
    tells it, even when the console's pushed status does not show that transfer yet (a
    loaded server's updates come late): then it runs, and nothing is refused."""
    monkeypatch.setattr(publish_module, "PUSH_TICK", 3600.0)  # updates only when told
    controller = await rig.start_controller(transfer_timeout=120)
    server = ApiServer(AttachedCell(controller), rig.directory)
    await server.start()
    client = await attach(rig.directory)
    # The robot's pick-station sensor stays off as the first transfer starts: its program
    # waits in WAITI(1, 1), the transfer stays in flight until the sensor comes on.
    robot = rig.cell.robot
    held: list[bool] = []

    def hold_as_the_door_opens(name: str, on: bool) -> None:
        if name == "door_1" and on and not held:
            held.append(True)
            robot.set_input(1, False)

    rig.cell.plc.hooks.coil.append(hold_as_the_door_opens)
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    try:
        async with app.run_test(size=SIZE) as pilot:
            await wait_text(pilot, "attached to cellctl run")
            await pilot.press("1")
            await wait_text(pilot, "ROBOT (robot)", "s. OUT OF SERVICE")
            await pilot.press("d")  # RETURN HOME acts: the robot must leave automatic service
            await wait_text(pilot, "robot is in automatic service")
            # From here the console gets no update: its status shows the robot idle.
            controller.listeners.remove(server.changed)
            rig.post("wax-robot-base", 1, "R1")
            await rig.wait_for(lambda: robot.waiting_for == (1, True), "the transfer held", 60)
            assert rig.open_steps("transfer") and not app.snapshot["machines"]["robot"]["step"]
            await pilot.press("y")
            await wait_text(pilot, "robot: waiting for its step in flight to end (transfer")
            assert not rig.alarms(), rig.describe()
            robot.set_input(1, True)  # the sensor sees the blank: the transfer goes on
            controller.listeners.append(server.changed)
            server.changed()
            await wait_text(pilot, "robot: RETURN HOME: Home", "s. RETURN TO SERVICE", timeout=30)
            steps = [s for s in rig.journal.steps() if s.kind == "transfer"]
            assert steps and steps[0].state == "finished"  # the step in flight ended first
            await pilot.press("s", "y")
            await wait_text(pilot, "robot back in automatic service", timeout=20)
            await rig.wait_for(lambda: rig.order_state("R1") == "done", "R1 done", timeout=60)
            assert not rig.alarms(), rig.describe()
            await pilot.press("q")
    finally:
        await client.close()
        await server.close()


async def test_attached_console_says_when_the_controller_goes(rig: CellRig) -> None:
    await rig.start_controller()
    assert rig.controller is not None
    server = ApiServer(AttachedCell(rig.controller), rig.directory)
    await server.start()
    client = await attach(rig.directory)
    app = ConsoleApp(rig.directory, client, traffic_period=0.1)
    try:
        async with app.run_test(size=SIZE) as pilot:
            await wait_text(pilot, "attached to cellctl run")
            # The robot's traffic while attached: its rows (a row: time, direction, hex, text).
            await wait_text(pilot, "traffic: robot", " <<  ")
            await server.close()
            await wait_text(pilot, "DISCONNECTED: controller's API closed; attaching again")
            await pilot.press("1", "4")
            await wait_text(pilot, "robot: STATUS: the control API closed the connection")
            await wait_text(pilot, "traffic: robot (DISCONNECTED: the last bytes seen before)")
            # Another machine's menu: the pane follows it, with what it can show (nothing
            # seen of cnc1), not the robot's rows.
            await pilot.press("escape", "2", "4")
            await wait_text(pilot, "cnc1: STATUS: the control API closed the connection")
            shown = await wait_text(pilot, "traffic: cnc1 (DISCONNECTED", "no traffic seen on cnc1")
            assert "traffic: robot" not in shown and " <<  " not in shown and " >>  " not in shown
            # The controller's API back (a restarted `cellctl run`): the console attaches
            # again by itself, and acts through it.
            with contextlib.ExitStack() as held:
                if controller_holder(rig.directory) is None:
                    held.enter_context(acquire_controller_lock(rig.directory))
                server = ApiServer(AttachedCell(rig.controller), rig.directory)
                await server.start()
                await wait_text(pilot, "attached again to the controller at", timeout=20)
                # The open menu's machine, its traffic asked for again.
                await wait_text(pilot, "traffic: cnc1 (>> sent")
                assert "DISCONNECTED" not in screen_text(app)
                await pilot.press("escape", "1", "4")
                await wait_text(pilot, "robot: STATUS: robot state", timeout=20)
                await wait_text(pilot, "traffic: robot (>> sent")
                await pilot.press("q")
    finally:
        await client.close()
        await server.close()


@settings(max_examples=150, deadline=None)
@given(
    which=st.sampled_from(
        [
            ("robot", "download"),
            ("robot", "go"),
            ("mill", "init"),
            ("mill", "download"),
            ("mill", "load"),
            ("robot", "io_set"),
        ]
    ),
    partition=st.text(max_size=6),
    text=st.text(max_size=300),
    force=st.booleans(),
)
@example(which=("robot", "go"), partition="¹", text="", force=False)  # a digit int() refuses
def test_dialog_answers_give_parameters_or_a_usage_error(
    which: tuple[str, str], partition: str, text: str, force: bool
) -> None:
    """Whatever the operator types or picks, the dialog's check says what is wrong (a
    UsageError) or gives parameters the function accepts: nothing else comes out."""
    family, name = which
    fn = function(family, name)
    with tempfile.TemporaryDirectory() as folder:
        directory = Path(folder)
        (directory / "prog.txt").write_text(text, encoding="utf-8")
        raw = {"partition": partition, "program": "prog.txt", "force": force}
        raw |= {"input": partition, "on": force}  # IO SET's
        try:
            params = check_params(ConsoleMachine("m", family, "M"), fn, raw, directory)
        except UsageError as e:
            assert str(e)
        else:
            fn.check(params)  # accepted as it will be sent


def test_a_partition_out_of_range_is_refused_in_the_functions_own_result(tmp_path: Path) -> None:
    """The source's results: DOWNLOAD's 2 is "partition error", GO's 2 "starting function
    error" (as `cellctl robot go 6` says it); the console said "partition error" for both."""
    robot = ConsoleMachine("robot", "robot", "ROBOT")
    with pytest.raises(UsageError) as told:
        check_params(robot, function("robot", "go"), {"partition": "6"}, tmp_path)
    assert str(told.value).endswith("partition must be 1 to 5, not 6 (starting function error)")


def test_a_dialog_tells_every_wrong_answer_at_once(tmp_path: Path) -> None:
    """A partition out of range is told with a missing file, not only once the file is found
    (the operator would fix one answer, press Enter, and only then hear of the other)."""
    fn = function("robot", "download")
    robot = ConsoleMachine("robot", "robot", "ROBOT")
    raw = {"partition": "6", "program": "nowhere.rec"}
    with pytest.raises(UsageError) as told:
        check_params(robot, fn, raw, tmp_path)
    assert str(told.value).splitlines() == [
        "nowhere.rec: could not open file: no such file",
        "partition must be 1 to 5, not 6 (partition error)",
    ]
    (tmp_path / "nowhere.rec").write_text("")  # an empty program: its own problem, still both
    with pytest.raises(UsageError) as told:
        check_params(robot, fn, raw, tmp_path)
    assert "partition must be 1 to 5, not 6 (partition error)" in str(told.value).splitlines()
    assert len(str(told.value).splitlines()) >= 2
