"""Every fault switch of every emulator, switched on in the middle of a run.

Each ends in recovery (the step retried, the machine re-initialized) or in a held part and an
alarm; then the operator switches the fault off, clears the alarms with ``cellctl alarm clear``,
releases what is held with ``cellctl part release`` after looking at the part, and the run
completes: every order done, no part lost, no part cut twice by one mill.
"""

from __future__ import annotations

import asyncio
import dataclasses
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from cellctl.cell.causes import ESTOP
from cellctl.cell.config import load_cell
from cellctl.cell.controller import CellController
from cellctl.cell.model import ControllerOptions
from cellctl.clock import current_clock
from cellctl.emulators.cell import EXAMPLE_CELL, EmulatedCell, real_cell_toml
from cellctl.errors import MachineInUse
from cellctl.kinds.dyna2400.driver import MillConfig
from cellctl.testing.rig import CellRig


@dataclass(frozen=True)
class Case:
    fault: str  # MACHINE:NAME[=ARG], as `cellctl emulate cell --fault` takes it
    alarm_machine: str
    alarm_text: str  # regular expression an alarm of alarm_machine must match: the cause
    held: bool | None  # the fault holds a part (False: it never does; None: if the arm moved)
    out_of_service: bool = False  # the machine keeps failing: taken out of service
    also: str | None = None  # a second fault that makes the first one matter


async def resolve_until_done(rig: CellRig) -> None:
    """The operator resolves what the cell holds, again each time it needs them, until every
    order is done (at most 20 times)."""
    for _ in range(20):
        if rig.all_done():
            return
        await rig.operator_resolves()
        await rig.wait_for(
            lambda: rig.all_done() or rig.held_parts() or rig.journal.active_alarms(),
            "the run to complete or to need the operator again",
            timeout=30,
        )
    assert rig.all_done(), rig.describe()


CASES = [
    # A robot fault is alarmed as its cause (its status, its link), whether the monitor or
    # a transfer sees it first; a transfer it cut short holds its part, one it stopped
    # before the arm moved leaves the part where it was.
    Case("robot:power-off", "robot", r"^power failure$", None),
    Case("robot:servo-error", "robot", r"^servo error$", None),
    Case("robot:drop", "robot", r"^link closed by the other end$", None),
    Case("robot:silent", "robot", r"^robot not answering$", None),
    # Seen idle (lost readiness) or as a cut is sent (CTS low): whichever comes first.
    Case("cnc2:never-ready", "cnc2", r"lost readiness|CTS low", False, out_of_service=True),
    # no-next matters when the mill is set up again: after a dropped block it is.
    Case("cnc2:no-next", "cnc2", r"^link closed by the other end$", True, also="cnc2:drop=3"),
    Case("cnc2:drop=3", "cnc2", r"^link closed by the other end$", True),
    Case("cnc2:stall", "cnc2", r"needs inspection: .* still running", True),
    Case("plc:drop", "plc", r"PLC not answering|link closed by the other end", False),
    Case("plc:silent", "plc", r"^PLC not answering$", False),
    # A door that does not leave its end position is stuck: caught before the arm moves
    # or the cut starts, so no part is held.
    Case(
        "plc:stuck-door=2", "plc", r"door of CNC 2 did not leave its (closed|open) position", False
    ),
    Case("plc:no-pallet", "plc", r"no pallet", False),
    Case("plc:estop", "plc", r"emergency stop", False),
]


def ids(case: Case) -> str:
    return case.fault


@pytest.mark.parametrize("case", CASES, ids=ids)
@pytest.mark.virtual
async def test_fault_during_a_run_ends_in_recovery_or_a_held_part(
    tmp_path: Path, case: Case
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 2, "A")
        # Some steps done: the first part has been roughed on cnc1. The fault comes as the
        # transfer after that cut opens cnc1's door, before the arm moves: the same moment
        # on every run, however fast the controller gets there.
        switched: list[str] = []

        def switch_as_the_door_opens(name: str, on: bool) -> None:
            if name == "door_1" and on and not switched and rig.finished_steps("machine") >= 1:
                switched.extend(f for f in (case.fault, case.also) if f)
                for fault in switched:
                    rig.switch_on(fault)

        rig.cell.plc.hooks.coil.append(switch_as_the_door_opens)
        controller = await rig.start_controller(fail_limit=3, retries=2)
        await rig.wait_for(lambda: switched, "first cut done, the fault switched on")
        if case.fault == "plc:no-pallet":
            rig.post("wax-toy-mill-table", 1, "B")  # more work: a pallet is asked for

        def alarmed() -> list[object]:
            return [
                a
                for a in rig.journal.alarms()
                if a.machine == case.alarm_machine and re.search(case.alarm_text, a.text)
            ]

        await rig.wait_for(alarmed, f"an alarm on {case.alarm_machine}: {case.alarm_text}")
        assert rig.reports("alarm-raised")
        if case.held:
            held = await rig.wait_for(rig.held_parts, "a part held")
            assert all(p.note for p in held)
            await rig.wait_for(lambda: rig.order_state("A") == "held", "order A held")
        if case.out_of_service:
            await rig.wait_for(
                lambda: not controller.machines[case.alarm_machine].in_service,
                f"{case.alarm_machine} out of service",
            )
            assert case.alarm_machine in rig.journal.machines_out_of_service()
            assert rig.alarms(case.alarm_machine, "out-of-service")
        # One alarm for the fault, the cause's, however many steps met it (taken out of
        # service is told on its own): counted once the cell is at rest, so an alarm that
        # any later look, retry, recovery or deadline would still raise is in the count.
        await rig.wait_quiet()
        raised = [a for a in rig.journal.alarms() if a.code != "out-of-service"]
        assert len(raised) == 1, rig.describe()
        # Nothing is lost while the fault lasts.
        parts = len(rig.journal.parts())
        assert parts == 2 + (case.fault == "plc:no-pallet")
        assert all(p.status != "scrapped" for p in rig.journal.parts())

        await rig.switch_off(case.fault)

        await resolve_until_done(rig)
        await rig.stop_controller()

        assert all(p.status == "done" for p in rig.journal.parts()), rig.describe()
        assert rig.journal.machines_out_of_service() == {}
        assert rig.cut_twice() == {}, rig.describe()
        # Every part made: as many blanks, each cut by both mills.
        made = [r for r in rig.cell.runs_per_part().values() if r == {"cnc1": 1, "cnc2": 1}]
        assert len(made) == parts, rig.describe()


@pytest.mark.virtual
async def test_corrupt_checksums_are_read_again_without_holding_anything(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 2, "A")
        controller = await rig.start_controller()
        await rig.wait_for(lambda: rig.finished_steps("machine") >= 1, "first cut done")
        rig.switch_on("robot:corrupt-checksum=2")
        await rig.wait_for(lambda: "corrupt-checksum" not in rig.cell.robot.faults, "2 bad reads")
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        await rig.stop_controller()
        assert rig.held_parts() == []
        assert rig.journal.alarms() == []
        assert all(s.state == "finished" for s in rig.journal.steps())
        assert controller.machines["robot"].failures == 0
        assert rig.cut_twice() == {}


@pytest.mark.virtual
async def test_a_robot_reject_is_reset_and_retried_a_bounded_number_of_times(
    tmp_path: Path,
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 1, "A")

        # The power goes as cnc1's door opens for the transfer after the first cut: the
        # program is in the robot, the arm has not moved (the doors open before it starts).
        def power_off_as_the_door_opens(name: str, on: bool) -> None:
            if name == "door_1" and on and rig.finished_steps("machine") >= 1:
                rig.switch_on("robot:power-off")

        rig.cell.plc.hooks.coil.append(power_off_as_the_door_opens)
        controller = await rig.start_controller(retries=2)
        await rig.wait_for(lambda: "power-off" in rig.cell.robot.faults, "the power off")
        await rig.wait_for(
            lambda: [s for s in rig.journal.steps() if s.state == "failed"], "a failed transfer"
        )
        retries = [e.text for e in controller.events if "reset and retry" in e.text]
        assert len(retries) == 2, f"{retries}\n{rig.describe()}"
        assert all("manipulator power off" in text for text in retries)
        # The arm never moved: the part is still in cnc1's vise, not held (nothing to
        # inspect), and no transfer starts while the robot's status says power failure.
        assert rig.cell.vise[1] == "P1"
        assert rig.held_parts() == []
        assert [(a.machine, a.text) for a in rig.journal.active_alarms()] == [
            ("robot", "power failure")
        ]
        await asyncio.sleep(controller.options.poll_period * 3)
        failed = [s for s in rig.journal.steps() if s.state == "failed"]
        assert [(s.kind, s.program) for s in failed] == [("transfer", "cnc1_to_cnc2")]
        await rig.switch_off("robot:power-off")
        await rig.operator_resolves()
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        await rig.stop_controller()
        assert rig.cell.runs_per_part() == {"P1": {"cnc1": 1, "cnc2": 1}}


async def cnc2_out_of_service(rig: CellRig, parts: int) -> tuple[CellController, Any]:
    """An order of ``parts``, its first cut done, then cnc2 never ready again: the controller
    (failing twice takes a mill out) and cnc2's out-of-service alarm."""
    rig.post("wax-robot-base", parts, "A")
    controller = await rig.start_controller(fail_limit=2)
    await rig.wait_for(lambda: rig.finished_steps("machine") >= 1, "first cut done")
    rig.switch_on("cnc2:never-ready")
    await rig.wait_for(lambda: rig.alarms("cnc2", "out-of-service"), "cnc2 taken out of service")
    return controller, rig.alarms("cnc2", "out-of-service")[0]


@pytest.mark.virtual
async def test_a_mill_out_of_service_returns_when_its_alarm_is_cleared(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        controller, out = await cnc2_out_of_service(rig, 2)
        assert "failed 2 times in a row" in out.text
        assert not controller.machines["cnc2"].in_service
        # Out of service: no step starts on cnc2; no part is lost (one may be held).
        assert all(s.machine != "cnc2" for s in rig.open_steps("machine"))
        assert {p.status for p in rig.journal.parts()} <= {"waiting", "active", "held"}
        await rig.switch_off("cnc2:never-ready")
        result = await rig.cli("alarm", "clear", str(out.id))
        assert result.exit_code == 0 and f"alarm {out.id} cleared" in result.output
        # Its out-of-service alarm cleared, it returns (the operator clears the rest too).
        await rig.clear_alarms()
        await rig.wait_for(lambda: controller.machines["cnc2"].in_service, "cnc2 back in service")
        assert rig.journal.machines_out_of_service() == {}
        await resolve_until_done(rig)
        await rig.stop_controller()
        assert rig.journal.machines_out_of_service() == {}
        assert rig.cut_twice() == {}
        # Cleared by who cleared it: the local user at the command line, the rig's operator.
        cleared = [r.text for r in rig.reports("alarm-cleared")]
        assert any(f"alarm {out.id} cleared by local:" in text for text in cleared), cleared


@pytest.mark.virtual
async def test_a_mill_put_back_in_service_returns_its_alarm_to_normal(tmp_path: Path) -> None:
    """`machine cnc2 in` ends what its out-of-service alarm stood for: the alarm returns to
    normal (open until cleared) and no longer counts cnc2 down in the shift report."""
    async with CellRig(tmp_path / "cell") as rig:
        controller, out = await cnc2_out_of_service(rig, 1)
        await rig.switch_off("cnc2:never-ready")
        # The operator's `machine cnc2 in` (machines.in_service), its alarm not cleared first.
        back = await controller.set_service("cnc2", True)
        assert back.startswith("cnc2 back in automatic service"), back
        alarm = rig.journal.get_alarm(out.id)
        assert alarm.returned is not None and alarm.state != "cleared", alarm
        assert controller.machines["cnc2"].in_service
        await rig.stop_controller()


@pytest.mark.virtual
async def test_a_robot_that_failed_its_start_up_returns_its_alarm_once_initialized(
    tmp_path: Path,
) -> None:
    """A robot silent as the controller starts: its start-up fails (one alarm, its cause's:
    "robot not answering"). Answering again, it is initialized by the next transfer: the
    alarm returns to normal (open until the operator clears it), as docs/api.md says a
    condition gone does."""
    async with CellRig(tmp_path / "cell") as rig:
        rig.switch_on("robot:silent")
        rig.post("wax-robot-base", 1, "A")
        await rig.start_controller()
        (failed,) = await rig.wait_for(lambda: rig.alarms("robot"), "the start-up's alarm")
        assert failed.text == "robot not answering", failed
        await rig.switch_off("robot:silent")
        await rig.wait_for(lambda: rig.finished_steps("transfer") >= 1, "a transfer", 120)

        def back() -> object:
            return rig.journal.get_alarm(failed.id).returned

        await rig.wait_for(back, "the start-up's alarm returned to normal")
        assert rig.journal.get_alarm(failed.id).state != "cleared"
        await rig.stop_controller()


@pytest.mark.virtual
async def test_a_mill_ready_again_after_its_setup_stop_returns_its_alarm(tmp_path: Path) -> None:
    """cnc1's operator does not finish its setup (no NEXT): "not ready ... after its setup".
    Once NEXT is pressed the mill is ready: the alarm returns to normal (open until cleared)."""
    async with CellRig(tmp_path / "cell") as rig:
        rig.switch_on("cnc1:no-next")
        rig.post("wax-robot-base", 1, "A")
        await rig.start_controller()
        (waited,) = await rig.wait_for(
            lambda: rig.alarms("cnc1", "readiness"), "the setup's readiness alarm", 300
        )
        assert "after its setup" in waited.text, waited.text
        await rig.switch_off("cnc1:no-next")

        def back() -> object:
            return rig.journal.get_alarm(waited.id).returned

        await rig.wait_for(back, "the readiness alarm returned to normal", 120)
        assert rig.journal.get_alarm(waited.id).state != "cleared"
        await rig.stop_controller()


@pytest.mark.parametrize("time_scale", [1.0, 50.0, 1000.0])
async def test_the_emulated_cell_writes_the_real_deadlines_scaled(
    tmp_path: Path, time_scale: float
) -> None:
    """What `cellctl emulate cell` writes: the real cell's deadlines for the machines' work,
    divided by the time scale, never below 5 s; the poll period stays the real cell's."""
    cell = EmulatedCell(time_scale=time_scale)
    try:
        await cell.start(tmp_path / "cell")
        config = load_cell(tmp_path / "cell")
    finally:
        await cell.close()
    options = ControllerOptions.from_config(config)
    real = load_cell(EXAMPLE_CELL)
    real_options = ControllerOptions.from_config(real)
    assert options.poll_period == real_options.poll_period
    for key in ("transfer_timeout", "interlock_timeout", "pallet_timeout"):
        want = max(5.0, getattr(real_options, key) / time_scale)
        assert getattr(options, key) == pytest.approx(want), key
    for mill in config.mills:
        mc = MillConfig.from_options(mill.options)
        assert mc.setup_timeout == pytest.approx(max(5.0, 120.0 / time_scale))
        assert mc.block_extra == pytest.approx(max(5.0, 60.0 / time_scale))


@pytest.mark.virtual
async def test_a_pallet_that_waited_is_taken_without_a_no_pallet_alarm(tmp_path: Path) -> None:
    """A pallet that came when asked, then waited longer than ``pallet_timeout`` for the
    robot, is no overdue pallet when the robot lifts it away: the request was served."""
    async with CellRig(tmp_path / "cell") as rig:
        plc = rig.cell.plc
        # A slow conveyor (0.5 s here): the robot is taken out of service while it runs.
        plc.timing = dataclasses.replace(plc.timing, conveyor_s=0.5 * rig.cell.time_scale)
        asked = asyncio.Event()
        plc.hooks.coil.append(lambda name, on: asked.set() if name == "pallet_request" else None)
        controller = await rig.start_controller()
        rig.post("wax-robot-base", 1, "A")
        async with asyncio.timeout(30):
            await asked.wait()
        await controller.set_service("robot", False, "teach pendant")
        await rig.wait_for(lambda: plc.inputs["pallet_present"], "the pallet delivered")
        # Longer than pallet_timeout with the pallet waiting at the pick-up.
        await rig.wait_quiet(span=2 * controller.options.pallet_timeout)
        await controller.set_service("robot", True)
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        await rig.wait_quiet()
        await rig.stop_controller()
        assert rig.journal.alarms() == [], rig.describe()
        assert plc.pallets_delivered == 1


@pytest.mark.virtual
async def test_no_pallet_is_one_alarm_and_the_pallet_comes_once_fixed(tmp_path: Path) -> None:
    """A conveyor that ignores requests: one alarm however often it is asked again; once the
    operator has fixed it and cleared the alarm, the request made before the fix is asked
    again, and no second alarm follows. Counted once the cell is at rest."""
    async with CellRig(tmp_path / "cell") as rig:
        rig.switch_on("plc:no-pallet")
        await rig.start_controller()
        rig.post("wax-robot-base", 1, "A")
        await rig.wait_for(lambda: rig.alarms("plc", "conveyor"), "the conveyor's alarm")
        await rig.wait_quiet()
        assert len(rig.journal.alarms()) == 1, rig.describe()
        await rig.switch_off("plc:no-pallet")
        await rig.operator_resolves()
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        await rig.wait_quiet()
        await rig.stop_controller()
        assert [(a.machine, a.code) for a in rig.journal.alarms()] == [("plc", "conveyor")], (
            rig.describe()
        )
        assert rig.cell.plc.pallets_delivered == 1


@pytest.mark.virtual
async def test_an_emergency_stop_during_a_transfer_is_one_alarm_naming_it(tmp_path: Path) -> None:
    """The E-stop pressed while the arm is in CNC 1 (the part in its gripper, the vise
    opening): the vise stops where it is, the transfer cannot end. Its failure is the stop's:
    one alarm, the stop's, the part held where the arm left it; the batch finishes once the
    operator released the stop, cleared the alarm and released the part."""
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 2, "A")
        pressed: list[str] = []

        def estop_as_the_vise_opens(port: int, value: bool) -> None:
            # Output 1 low: cnc1_to_cnc2 opens CNC 1's vise with the part in the gripper.
            if port == 1 and not value and not pressed and rig.finished_steps("machine") >= 1:
                pressed.append("plc:estop")
                rig.switch_on("plc:estop")

        rig.cell.robot.output_hooks.append(estop_as_the_vise_opens)
        await rig.start_controller()
        await rig.wait_for(lambda: pressed, "the E-stop pressed during cnc1_to_cnc2")
        held = await rig.wait_for(rig.held_parts, "the part in the gripper held")
        await rig.wait_quiet()
        assert [(a.machine, a.code, a.text) for a in rig.journal.alarms()] == [
            ("plc", "estop", ESTOP.text)
        ], rig.describe()
        # The held part and its failed step say why, in the same words.
        assert [p.id for p in rig.held_parts()] == [held[0].id]
        assert "emergency stop" in (held[0].note or ""), held[0].note
        failed = [s for s in rig.journal.steps() if s.state == "failed"]
        assert [(s.kind, s.program) for s in failed] == [("transfer", "cnc1_to_cnc2")]
        assert rig.reports("step-failed")
        assert all("emergency stop" in r.text for r in rig.reports("step-failed"))

        await rig.switch_off("plc:estop")
        await resolve_until_done(rig)
        await rig.stop_controller()
        assert all(p.status == "done" for p in rig.journal.parts()), rig.describe()
        assert rig.cut_twice() == {}, rig.describe()
        assert [(a.machine, a.code) for a in rig.journal.alarms()] == [("plc", "estop")]


@pytest.mark.virtual
async def test_the_plcs_emergency_stop_released_restarts_nothing(tmp_path: Path) -> None:
    """The PLC's E-stop pressed between two steps, then released: the cell paused with it
    and stays paused (no step starts, `resume` refused) until the operator cleared the
    stop's alarm and resumed, as after `cellctl estop`; then the batch finishes."""
    async with CellRig(tmp_path / "cell") as rig:
        clock = current_clock()
        rig.post("wax-robot-base", 2, "A")
        controller = await rig.start_controller()
        await rig.wait_for(lambda: rig.finished_steps("machine") >= 1, "a first cut")
        rig.switch_on("plc:estop")
        await rig.wait_for(lambda: rig.alarms("plc", "estop"), "the stop's alarm")
        await rig.wait_for(lambda: controller.paused, "the cell paused")
        await rig.switch_off("plc:estop")
        released = clock.now()
        await rig.wait_for(lambda: controller.inputs.get("estop_ok"), "the release seen")
        await clock.sleep(120)  # a couple of minutes of a released button
        assert not [s for s in rig.journal.steps() if s.started > released], rig.describe()
        assert controller.paused, rig.describe()
        with pytest.raises(MachineInUse, match=r"the emergency stop's alarm \d+ is not cleared"):
            controller.resume()
        await resolve_until_done(rig)
        await rig.stop_controller()
        assert all(p.status == "done" for p in rig.journal.parts()), rig.describe()
        assert rig.cut_twice() == {}, rig.describe()


@pytest.mark.virtual
async def test_a_door_stuck_during_a_transfer_is_named_in_its_alarm(tmp_path: Path) -> None:
    """CNC 2's door sticks half-way open during cnc1_to_cnc2 (it left its closed position,
    so the transfer started): the robot waits for it with the part in its gripper. At the
    interlock's deadline, not the transfer's, the alarm names the door, as a stuck door
    outside a transfer is named (the PLC's interlock); the robot's cycle is stopped, so the
    arm does not go on by itself once the door is freed; the part is held, and the batch
    finishes once the operator freed the door and resolved."""
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 2, "A")
        stuck: list[str] = []

        def stick_as_it_leaves(name: str, value: bool) -> None:
            moving = name == "door_closed_2" and not value
            if moving and not stuck and rig.finished_steps("machine") >= 1:
                stuck.append("plc:stuck-door=2")
                # Once the PLC has set the door moving: it stops half-way.
                asyncio.get_running_loop().call_soon(rig.switch_on, stuck[0])

        rig.cell.plc.hooks.input.append(stick_as_it_leaves)
        controller = await rig.start_controller()
        await rig.wait_for(lambda: stuck, "CNC 2's door stuck during cnc1_to_cnc2")
        held = await rig.wait_for(rig.held_parts, "the part in the gripper held")
        await rig.wait_quiet()
        timeout = controller.options.interlock_timeout
        assert timeout < controller.options.transfer_timeout
        assert [(a.machine, a.code, a.text) for a in rig.journal.alarms()] == [
            ("plc", "interlock", f"door of CNC 2 did not open within {timeout:g} s")
        ], rig.describe()
        assert rig.cell.plc.inputs["door_open_2"] is False
        assert "door of CNC 2" in (held[0].note or ""), held[0].note
        # Stopped where it waited, the part still in its gripper.
        assert not rig.cell.robot.running and rig.cell.gripper is not None, rig.describe()
        # The robot is not at fault: no failure counts against it.
        assert controller.machines["robot"].failures == 0

        await rig.switch_off(stuck[0])
        await resolve_until_done(rig)
        await rig.stop_controller()
        assert all(p.status == "done" for p in rig.journal.parts()), rig.describe()
        assert rig.cut_twice() == {}, rig.describe()
        assert [(a.machine, a.code) for a in rig.journal.alarms()] == [("plc", "interlock")]


@pytest.mark.virtual
async def test_an_emergency_stop_as_a_transfers_door_opens_ends_it_at_once(
    tmp_path: Path,
) -> None:
    """The E-stop pressed as CNC 2's door leaves its closed position for cnc1_to_cnc2 (the
    robot waits for it, the part in its gripper): the door stops half-way. The transfer
    does not wait out the interlock's deadline for it: it ends at once, one alarm, the
    stop's, the part held "cut short by the emergency stop"."""
    async with CellRig(tmp_path / "cell") as rig:
        clock = current_clock()
        rig.post("wax-robot-base", 1, "A")
        pressed: list[float] = []

        def estop_as_the_door_leaves(name: str, value: bool) -> None:
            if name == "door_closed_2" and not value and not pressed:
                pressed.append(clock.now())
                asyncio.get_running_loop().call_soon(rig.switch_on, "plc:estop")

        rig.cell.plc.hooks.input.append(estop_as_the_door_leaves)
        controller = await rig.start_controller()
        (held,) = await rig.wait_for(rig.held_parts, "the part in the gripper held")
        await rig.wait_quiet()
        assert [(a.machine, a.code) for a in rig.journal.alarms()] == [("plc", "estop")]
        assert "cut short by the emergency stop" in (held.note or ""), held.note
        (failed,) = [s for s in rig.journal.steps() if s.state == "failed"]
        assert failed.program == "cnc1_to_cnc2" and failed.ended is not None
        # Within a look or two of the press, not at the door's deadline.
        assert failed.ended - pressed[0] < controller.options.interlock_timeout / 2
        assert not rig.cell.robot.running

        await rig.switch_off("plc:estop")
        await resolve_until_done(rig)
        await rig.stop_controller()
        assert all(p.status == "done" for p in rig.journal.parts()), rig.describe()
        assert rig.cut_twice() == {}, rig.describe()


async def test_an_emulated_cell_of_an_emulated_cells_directory_is_the_real_cells_emulation(
    tmp_path: Path,
) -> None:
    """An emulated cell's directory as the template (``cellctl emulate cell --template``, a
    plan of an emulated cell): what the first emulation wrote is undone first, so the file
    holds one time scale, one options table per machine, and the real cell's deadlines
    scaled once; the real cell's file read back from it is the example's own."""
    cells = [EmulatedCell(time_scale=100.0)]
    try:
        await cells[0].start(tmp_path / "first")
        cells += [EmulatedCell(time_scale=2.0, template=tmp_path / "first")]
        cells += [EmulatedCell(time_scale=2.0)]
        await cells[1].start(tmp_path / "again")
        await cells[2].start(tmp_path / "fresh")
        written = (tmp_path / "again" / "cell.toml").read_text()
        config = load_cell(tmp_path / "again")
        want = load_cell(tmp_path / "fresh")
    finally:
        for cell in cells:
            await cell.close()
    assert written.count("time_scale = 2 ") == 1, written
    assert config.raw["cell"]["time_scale"] == 2
    assert ControllerOptions.from_config(config) == ControllerOptions.from_config(want)
    for name in ("cnc1", "cnc2"):
        assert config.raw["machines"][name]["options"] == want.raw["machines"][name]["options"]
    real = tomllib.loads(real_cell_toml((tmp_path / "first" / "cell.toml").read_text()))
    example = tomllib.loads((EXAMPLE_CELL / "cell.toml").read_text())
    for table in (real, example):
        for machine in table["machines"].values():
            machine.pop("link")
        table["plc"].pop("url")
    assert real == example


@pytest.mark.virtual
async def test_a_part_released_to_be_cut_again_after_an_emergency_stop_is_cut(
    tmp_path: Path,
) -> None:
    """The way out of an emergency stop with the part left in the mill to be cut again
    (`part release --redo`): on resume the halted mill is set up anew over it (END took its
    setup; without one it would never show ready and would go out of service)."""
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 1, "A")
        controller = await rig.start_controller()
        await rig.wait_for(lambda: rig.open_steps("machine"), "a cut in flight")
        await controller.emergency_stop("guard opened")
        held = rig.held_parts()
        assert held and all(p.location in rig.cell.mills for p in held), rig.describe()
        mills = rig.cell.mills.values()
        await rig.wait_for(lambda: all(m.display == "READY" for m in mills), "mills READY")
        await rig.clear_alarms()
        for part in held:
            released = await rig.cli("part", "release", part.id, "--redo")
            assert released.exit_code == 0, released.output
        assert controller.resume() == "resumed"
        await rig.wait_for(rig.all_done, "order A done", timeout=120)
        await rig.stop_controller()
        assert not rig.alarms(code="out-of-service"), rig.describe()
