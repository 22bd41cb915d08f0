"""The factory dispatching by the cells' own plans, end to end: a real Mosquitto, two emulated
cells with their ``cellctl run`` controllers (``[mailbox] plan_period``: each plans its open
work and publishes when it finishes) and ``cellctl factory run`` with ``[dispatch] estimate =
"plan"``, each its own process (tests/factory_plant.py).

cell1 has cnc1 out of service and one robot base to make: its bottleneck bound counts one
part, but its plan, played with cnc1 out, does not finish it within the plan's horizon. cell2
holds two robot bases for its operator: its bound counts both, its plan (which does not guess
the operator's word) has nothing to play. By the bound alone the next order would go to cell1
were its cnc1 in service (with cnc1 out, on the part's route, no estimate sends it there); by
the plans it goes to cell2, and the factory says so.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.cell.commands import OPERATOR_OUT
from cellctl.cell.config import CONVEYOR
from cellctl.factory.dispatch import BOUND, Estimating, choose
from cellctl.factory.emulated import EmulatedFactory
from cellctl.factory.store import QUEUED
from cellctl.ui.cli import main
from tests.factory_plant import Plant

#: Seconds of the real machines' time a cell's plan plays ahead: cell1's stops there.
HORIZON_S = 300


def plan_everywhere(plant: Plant) -> None:
    """Each cell plans its own work; the factory dispatches by the plans."""
    for name in plant.names:
        toml = plant.cell_dir(name) / "cell.toml"
        text = toml.read_text(encoding="utf-8")
        assert "[mailbox]\n" in text
        text = text.replace(
            "[mailbox]\n", f"[mailbox]\nplan_period = 600\nplan_horizon = {HORIZON_S}\n", 1
        )
        toml.write_text(text, encoding="utf-8")
    factory = plant.directory / "factory.toml"
    factory.write_text(
        factory.read_text(encoding="utf-8") + '\n[dispatch]\nestimate = "plan"\n', "utf-8"
    )


@pytest.mark.timeout(180)  # beyond the plant's own deadlines: they say more
async def test_the_factory_sends_an_order_by_the_cells_plans_not_their_bounds(
    tmp_path: Path,
) -> None:
    plant = Plant(tmp_path / "plant", cells=2)
    # Real time: nothing in either cell moves (cnc1 out, the parts held), and a plan's
    # seconds are the cells' own.
    plant.emulated = EmulatedFactory(
        plant.directory, cells=2, time_scale=1.0, poll_period=0.1, factory_poll=0.1
    )
    async with plant:
        plan_everywhere(plant)
        plant.journals["cell1"].set_machine_service("cnc1", False, f"{OPERATOR_OUT}: repair")
        plant.mailboxes["cell1"].post_order("wax-robot-base", 1, 0, order_id="L1")
        held, _ = plant.mailboxes["cell2"].post_order("wax-robot-base", 2, 0, order_id="H1")
        plant.mailboxes["cell2"].set_order_state("H1", "accepted")
        for part in plant.journals["cell2"].create_parts(held):
            plant.journals["cell2"].move_part(part.id, CONVEYOR, 0)
            plant.journals["cell2"].hold_part(part.id, "held for the operator")
        await plant.start_all()

        def planned() -> bool:
            cells = plant.store.cells()
            return (
                all(
                    c.state.get("planned_at") is not None and c.state.get("parts_open")
                    for c in cells.values()
                )
                and cells["cell1"].state.get("plan_finish_s", 0) > 0
            )

        await plant.wait_for(planned, "both cells' plans of their open work at the factory")
        cells = plant.store.cells()
        one, two = cells["cell1"].state, cells["cell2"].state
        # What each said: cell1's bound below cell2's, its plan at the horizon; cell2's none.
        assert one["finish_estimate_s"] < two["finish_estimate_s"]
        assert one["plan_finish_s"] == HORIZON_S and two["plan_finish_s"] == 0

        _, new = plant.store.submit("wax-robot-base", 1, order_id="N1")
        assert new
        sent = await plant.wait_for(
            lambda: [o for o in plant.store.orders() if o.id == "N1" and o.state != "queued"],
            "order N1 sent to a cell",
        )
        assert sent[0].cell == "cell2", plant.describe()
        # The factory logs why in the commit that marks the order sent: it is there now.
        events = [
            e.text
            for e in plant.store.events()
            if e.order_id == "N1" and e.text.startswith("order N1: cell")
        ]
        assert any(t.startswith("order N1: cell2 finishes it earliest by its plan") for t in events)
        # By the bound alone, from the very same states, cell1 would have had it had its cnc1
        # been in service; with cnc1 out (on the robot base's route) the bound passes it over
        # too.
        queued = dataclasses.replace(plant.store.get("N1"), state=QUEUED, cell=None)
        others = [o for o in plant.store.orders() if o.id != "N1"]
        assert choose(queued, cells, others, Estimating(BOUND))[0] == "cell2"
        machines = {**one["machines"], "cnc1": {**one["machines"]["cnc1"], "in_service": True}}
        serviced = dataclasses.replace(cells["cell1"], state={**one, "machines": machines})
        bound_pick = choose(queued, {**cells, "cell1": serviced}, others, Estimating(BOUND))
        assert bound_pick[0] == "cell1"

        # The factory's plan of its running cells: each asked through its own API, from its
        # state now (cell1 with cnc1 out of service, cell2 with its held parts and N1).
        args = ["factory", "--dir", str(plant.directory), "plan", "--shift", "5m", "--json"]
        result = await asyncio.to_thread(CliRunner().invoke, main, args)
        assert result.exit_code == 0, result.output
        plans = json.loads(result.output)
        assert sorted(plans) == ["cell1", "cell2"], plans
        [one_plan], [two_plan] = plans["cell1"]["plans"], plans["cell2"]["plans"]
        assert [(o["order_id"], o["finished"]) for o in one_plan["orders"]] == [("L1", None)]
        assert one_plan["busy_s"]["cnc1"] == 0
        assert "N1" in {o["order_id"] for o in two_plan["orders"]}
        assert two_plan["held_at_start"] == 2
