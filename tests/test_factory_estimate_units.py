"""The cells' estimates in one unit, end to end: a real Mosquitto, two emulated cells faster
than real time with their ``cellctl run`` controllers, and ``cellctl factory run``, each its
own process (tests/factory_plant.py).

A part type a cell has not made yet is estimated from its programs (the machines' own
seconds); one it has made, from what it measured (its own clock's seconds). On an emulated
cell the two differ by the time scale, so each cell says both in its own clock's seconds:
after cell A has made a wax-toy-mill-table and cell B has not, their ``bound_s`` for it are
alike, and of two more such orders each cell gets one (the one that measured the type does
not get everything while the other sits idle).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.factory.emulated import EmulatedFactory
from cellctl.factory.store import DONE, QUEUED, FactoryOrder
from tests.factory_plant import Plant

PART = "wax-toy-mill-table"
#: Fast enough for CI (a part in a few seconds), slow enough that the cells' fixed overheads
#: (polls, the broker) stay small beside the machines' time.
SCALE = 200.0


@pytest.mark.timeout(180)  # beyond the plant's own deadlines: they say more
async def test_a_cell_that_measured_a_type_and_one_that_did_not_compare_fairly(
    tmp_path: Path,
) -> None:
    plant = Plant(tmp_path / "plant", cells=2)
    plant.emulated = EmulatedFactory(
        plant.directory, cells=2, time_scale=SCALE, poll_period=0.1, factory_poll=0.1
    )
    async with plant:
        await plant.start_all()
        before = {name: c.part_types[PART] for name, c in plant.store.cells().items()}
        plant.submit([("T1", PART, 1)])
        await plant.wait_for(lambda: plant.done() == {"T1"}, "order T1 done")
        made = plant.store.get("T1").cell
        assert made is not None
        [idle] = [name for name in plant.names if name != made]

        def measured() -> bool:
            # The state the cell sent after T1: nothing open, the type measured.
            state = plant.store.cells()[made].state
            return state.get("orders_open") == 0 and state.get("parts_open") == 0

        await plant.wait_for(measured, f"{made}'s state after T1 at the factory")
        cells = plant.store.cells()
        after = {name: c.part_types[PART] for name, c in cells.items()}
        # The idle cell still says what it said before it was given anything.
        assert after[idle] == before[idle], (before, after)
        # One unit: the measured figure and the unmeasured one are alike (in two units
        # they differ by the time scale, 200 times).
        assert 0.5 < after[made] / after[idle] < 2, (before, after)

        plant.submit([("T2", PART, 1), ("T3", PART, 1)])

        def sent() -> list[FactoryOrder]:
            orders = [plant.store.get(i) for i in ("T2", "T3")]
            return orders if all(o.state != QUEUED for o in orders) else []

        orders = await plant.wait_for(sent, "orders T2 and T3 sent")
        assert sorted(o.cell or "" for o in orders) == plant.names, plant.describe()
        await plant.wait_for(
            lambda: {o.id for o in plant.store.orders([DONE])} >= {"T2", "T3"},
            "orders T2 and T3 done",
        )
