"""The whole cell end to end: the emulated robot (pty), mills (RFC 2217) and PLC (Modbus/TCP)
in this process, the controller driving them, orders in through the mailbox."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.testing.rig import CellRig


async def test_a_batch_of_orders_completes(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 2, "A")
        rig.post("wax-toy-mill-table", 1, "B")
        await rig.start_controller()
        await rig.wait_for(rig.all_done, "every order done", timeout=60)
        await rig.stop_controller()

        assert rig.mailbox.get_order("A").note == "2 made"
        parts = rig.journal.parts()
        assert [(p.id, p.status, p.location, p.route_index) for p in parts] == [
            ("A-1", "done", "out", 2),
            ("A-2", "done", "out", 2),
            ("B-1", "done", "out", 2),
        ]
        # Physically: three blanks went through, each cut once by each mill, all on the outfeed.
        assert rig.cell.runs_per_part() == {
            "P1": {"cnc1": 1, "cnc2": 1},
            "P2": {"cnc1": 1, "cnc2": 1},
            "P3": {"cnc1": 1, "cnc2": 1},
        }
        assert sorted(rig.cell.outfeed) == ["P1", "P2", "P3"]
        assert rig.cell.gripper is None and set(rig.cell.vise.values()) == {None}
        # The mailbox tells the system controller how it went.
        kinds = {r.kind for r in rig.mailbox.reports()}
        assert {"order-accepted", "step-started", "step-finished", "order-done"} <= kinds
        assert not rig.journal.active_alarms()


@pytest.mark.virtual
async def test_reposted_order_ids_are_harmless(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 1, "A")
        rig.post("wax-robot-base", 1, "A")  # the system controller posts again after a timeout
        await rig.start_controller()
        await rig.wait_for(rig.all_done, "order A done", timeout=60)
        rig.post("wax-robot-base", 1, "A")  # ... and again once it is done
        # The controller reads its mailbox once more on its way out.
        await rig.stop_controller()

        assert [o.id for o in rig.mailbox.orders()] == ["A"]
        assert rig.mailbox.get_order("A").state == "done"
        assert [p.id for p in rig.journal.parts()] == ["A-1"]
        assert rig.cell.runs_per_part() == {"P1": {"cnc1": 1, "cnc2": 1}}
        assert len(rig.reports("order-done")) == 1
        assert len(rig.reports("order-accepted")) == 1


@pytest.mark.virtual
async def test_unknown_part_type_is_rejected_and_the_rest_runs(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-teapot", 1, "X")
        rig.post("wax-toy-mill-table", 1, "B")
        await rig.start_controller()
        await rig.wait_for(lambda: rig.order_state("B") == "done", "order B done", timeout=60)
        await rig.stop_controller()
        assert rig.order_state("X") == "failed"
        assert any("wax-teapot" in r.text for r in rig.reports("order-rejected"))


@pytest.mark.virtual
async def test_stop_lets_the_steps_in_flight_finish(tmp_path: Path) -> None:
    """What SIGINT does to ``cellctl run``: no new step starts, running ones finish."""
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 2, "A")
        await rig.start_controller()
        await rig.wait_for(lambda: rig.open_steps("machine"), "a machining step in flight")
        await rig.stop_controller()

        assert rig.journal.open_steps() == []
        steps = rig.journal.steps()
        assert steps and all(s.state == "finished" for s in steps)
        assert rig.journal.recover().clean
        # Nothing half done: the next run carries on from where this one stopped.
        await rig.start_controller()
        await rig.wait_for(rig.all_done, "order A done after the restart", timeout=60)
        await rig.stop_controller()
        assert rig.held_parts() == []
        assert rig.cut_twice() == {}
