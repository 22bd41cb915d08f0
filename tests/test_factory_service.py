"""The factory and its cells' machines and parts, end to end: a real Mosquitto, emulated
cells with their ``cellctl run`` controllers and ``cellctl factory run``, each its own
process (tests/factory_plant.py).

- A cell with a machine its part type's route needs out of service gets no order of that
  type, however low its bound; when no cell can make it, the order waits, saying once which
  cells and why, and goes as soon as one can.
- The factory counts an order's parts made as the cell makes them, and its held parts by the
  cell's reports: done rises while the order runs, and a held part scrapped is no longer held.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from cellctl.cell.commands import OPERATOR_OUT
from cellctl.factory.emulated import EmulatedFactory
from cellctl.factory.store import DONE, HELD, IN_PROGRESS, QUEUED
from cellctl.testing.rig import cli
from cellctl.ui.cli import main
from tests.factory_plant import Plant

BASE = "wax-robot-base"  # its route: robot, cnc1, cnc2 (the example cell's)


def out_seen(plant: Plant, cell: str, machine: str, out: bool = True) -> bool:
    """The factory's last state of ``cell`` says ``machine`` is out of service (or in)."""
    seen = plant.store.cells().get(cell)
    if seen is None:
        return False
    machines = seen.state.get("machines") or {}
    return (machines.get(machine) or {}).get("in_service") is (not out)


async def operator(plant: Plant, cell: str, *args: str) -> str:
    result = await cli(plant.cell_dir(cell), *args)
    assert result.exit_code == 0, f"{args}: {result.output}\n{plant.describe()}"
    return result.output


@pytest.mark.timeout(240)  # beyond the plant's own deadlines: they say more
async def test_a_cell_with_a_machine_of_the_route_out_gets_no_order_until_one_can(
    tmp_path: Path,
) -> None:
    async with Plant(tmp_path / "plant", cells=2) as plant:
        # cell1's cnc2 is out: its bound is as low as cell2's, and lower once cell2 is busy.
        plant.journals["cell1"].set_machine_service("cnc2", False, f"{OPERATOR_OUT}: noise")
        await plant.start_all()
        await plant.wait_for(lambda: out_seen(plant, "cell1", "cnc2"), "cell1's cnc2 out")
        plant.submit([(f"D{n}", BASE, 1) for n in range(1, 4)])
        sent = await plant.wait_for(
            lambda: (
                [o for o in plant.store.orders() if o.state != QUEUED] == plant.store.orders()
                and plant.store.orders()
            ),
            "D1, D2 and D3 sent to a cell",
        )
        assert {o.cell for o in sent} == {"cell2"}, plant.describe()
        # The cell tells the factory which machines each part type needs.
        makes = plant.store.cells()["cell1"].state["part_types"][BASE]
        assert set(makes["machines"]) >= {"robot", "cnc1", "cnc2"}, makes

        # Now cell2's cnc2 goes out too: no cell can make a robot base.
        await operator(plant, "cell2", "machine", "cnc2", "out", "--reason", "spindle noise")
        await plant.wait_for(lambda: out_seen(plant, "cell2", "cnc2"), "cell2's cnc2 out")
        plant.submit([("W1", BASE, 1)])
        why = (
            f"waiting for a cell that can make {BASE} now "
            "(cell1 has cnc2 out of service; cell2 has cnc2 out of service)"
        )
        waits = f"order W1 waits: {why}"
        await plant.wait_for(
            lambda: any(e.text == waits for e in plant.store.events(limit=10_000)),
            "the factory says why W1 waits",
        )
        assert plant.store.get("W1").state == QUEUED and plant.store.get("W1").note == why

        # cell1's cnc2 comes back: W1 goes there, and is made.
        await operator(plant, "cell1", "machine", "cnc2", "in")
        await plant.wait_for(lambda: plant.store.get("W1").state == DONE, "W1 made")
        assert plant.store.get("W1").cell == "cell1"
        # Said once, in words, however many ticks it waited.
        texts = [e.text for e in plant.store.events(limit=10_000) if e.order_id == "W1"]
        assert texts.count(waits) == 1, texts


@pytest.mark.timeout(240)
async def test_the_factory_counts_parts_made_and_held_as_the_cell_reports_them(
    tmp_path: Path,
) -> None:
    async with Plant(tmp_path / "plant", cells=1) as plant:
        await plant.start_all()
        plant.submit([("K", BASE, 3)])
        journal = plant.journals["cell1"]

        def made() -> int:
            return sum(p.status == "done" for p in journal.parts(order_id="K"))

        # Killed mid-cut once a part is made: the restart holds the part it was cutting.
        await plant.wait_for(
            lambda: made() >= 1 and any(s.kind == "machine" for s in journal.open_steps()),
            "a part of K made, another being cut",
        )
        await plant.kill("cell1")
        assert any(s.kind == "machine" for s in journal.open_steps()), plant.describe()
        await plant.start("cell1")

        def held_now() -> set[str]:
            return {p.id for p in journal.parts(order_id="K", statuses=["held"])}

        def counted() -> bool:
            k = plant.store.get("K")
            held = held_now()
            return k.state == HELD and k.done == made() and set(k.held_parts) == held != set()

        # The restart holds the parts whose steps were in flight; the parts made count at
        # once, not when the order ends.
        await plant.wait_for(counted, "the factory counts K's parts made and held")
        k = plant.store.get("K")
        held = sorted(held_now())
        assert k.held == len(held) and k.done >= 1, plant.describe()

        # The operator takes each held part out and scraps it: held no longer, and the order
        # is held while one still is.
        for n, part_id in enumerate(held, start=1):
            out = await operator(plant, "cell1", "part", "scrap", part_id, "--taken-out")
            assert "scrapped" in out
            await plant.wait_for(
                lambda n=n: plant.store.get("K").scrapped == n, f"{part_id} scrapped at the factory"
            )
            k = plant.store.get("K")
            assert part_id not in k.held_parts and k.held == len(held) - n, plant.describe()
            if k.held:
                assert k.state == HELD, plant.describe()
            else:
                assert k.state in (IN_PROGRESS, DONE), plant.describe()
        await plant.wait_for(lambda: plant.store.get("K").state == DONE, "K done")
        k = plant.store.get("K")
        assert (k.done, k.held, k.scrapped) == (3 - len(held), 0, len(held)), plant.describe()
        assert made() == k.done


@pytest.mark.timeout(240)
async def test_the_factory_plan_of_running_cells_says_what_is_true(tmp_path: Path) -> None:
    """``cellctl factory plan`` over running cells: a wrong token is refused as a cell's own
    plan is (exit 7, the README's table); a cell whose open orders have all their parts held
    is said to be so, not to have no orders; a cell whose plan does not finish an order says
    so in the summary."""
    plant = Plant(tmp_path / "plant", cells=2)
    # Real time: nothing moves in either cell (the parts held, cnc1 out).
    plant.emulated = EmulatedFactory(
        plant.directory, cells=2, time_scale=1.0, poll_period=0.1, factory_poll=0.1
    )
    async with plant:
        mailbox, journal = plant.mailboxes["cell1"], plant.journals["cell1"]
        held, _ = mailbox.post_order(BASE, 2, 0, order_id="H1")
        mailbox.set_order_state("H1", "accepted")
        for part in journal.create_parts(held):
            journal.hold_part(part.id, "held for the operator")
        plant.journals["cell2"].set_machine_service("cnc1", False, f"{OPERATOR_OUT}: repair")
        plant.mailboxes["cell2"].post_order(BASE, 1, 0, order_id="L1")
        await plant.start_all()
        args = ["factory", "--dir", str(plant.directory), "plan", "--shift", "5m"]

        def factory_plan(env: dict[str, str] | None = None) -> Result:
            return CliRunner().invoke(main, args, env=env)

        refused = await asyncio.to_thread(factory_plan, {"CELLCTL_TOKEN": "wrongtoken"})
        assert refused.exit_code == 7, refused.output
        assert "cell1: " in refused.output and "cell2: " in refused.output, refused.output

        result = await asyncio.to_thread(factory_plan)
        assert result.exit_code == 0, result.output
        said = " ".join(result.output.split())
        assert (
            "cell1 not planned: nothing to plan: 1 open order, every part held: nothing plays "
            "until the operator releases them" in said
        ), result.output
        assert "cell2 on time 0, late 0, not finished 1, parts made 0" in said, result.output
