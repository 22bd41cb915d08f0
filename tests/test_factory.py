"""The factory end to end: a real Mosquitto on loopback, three emulated cells with their
``cellctl run`` controllers and ``cellctl factory run``, each its own process, and 30 orders
of both part types. Three faults, each in its own test: a cell controller killed with -9
mid-cut and started again, the broker stopped mid-batch and started again, the factory
controller killed with -9 and started again. After each, every order's parts were made once:

- from the mills' own logs (``EmulatedCell.runs_per_part``): every physical part cut once on
  each mill of its route, and as many parts cut as were ordered;
- from the reports: each order done in the factory's store, and in exactly one cell's
  SQLite mailbox (not cancelled), done there with its quantity of parts.

The plant is tests/factory_plant.py; the broker's ACLs, malformed messages and the command
line are in tests/test_factory_edges.py.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from cellctl.factory.store import DONE
from tests.factory_plant import DURING, FIRST, Plant


@pytest.fixture
async def plant(tmp_path: Path) -> AsyncIterator[Plant]:
    """Broker, three emulated cells, their controllers and the factory's, all running."""
    async with Plant(tmp_path / "plant") as p:
        await p.start_all()
        yield p


@pytest.mark.timeout(240)  # beyond the plant's own deadlines: they say more
async def test_a_cell_controller_killed_mid_cut_and_restarted(plant: Plant) -> None:
    plant.submit(FIRST)
    victim = await plant.wait_for(
        lambda: len(plant.done()) >= 3 and plant.cutting(), "a cell cutting, 3 orders done"
    )
    await plant.kill(victim)
    journal = plant.journals[victim]
    in_flight = {s.part_id: s for s in journal.open_steps()}
    assert any(s.kind == "machine" for s in in_flight.values()), plant.describe()
    plant.submit(DURING)  # they go to the cells still there
    await plant.wait_for(
        lambda: plant.store.cells()[victim].status == "offline", f"the factory sees {victim} gone"
    )
    # Its accepted orders wait for it: never sent elsewhere.
    waiting = {o.id for o in plant.store.orders() if o.cell == victim and o.state != DONE}
    assert waiting, plant.describe()
    await plant.start(victim)
    # The restart holds every part whose step was in flight: a cut is never run again by itself.
    await plant.wait_for(
        lambda: set(in_flight) <= {p.id for p in journal.parts(statuses=["held"])},
        "the interrupted parts held after the restart",
    )
    for part_id, step in in_flight.items():
        if step.kind == "machine":
            assert journal.get_part(part_id).note.startswith("needs inspection")
    await plant.finish(operator=True)
    plant.check_made_once()
    assert {o.id for o in plant.store.orders() if o.cell == victim} >= waiting
    held = [r for r in plant.mailboxes[victim].reports() if r.kind == "part-held"]
    assert {r.part_id for r in held} >= set(in_flight)


@pytest.mark.timeout(240)  # beyond the plant's own deadlines: they say more
async def test_the_broker_stopped_mid_batch_and_restarted(plant: Plant) -> None:
    plant.submit(FIRST)
    await plant.wait_for(
        lambda: len(plant.done()) >= 3 and plant.cutting(), "a cell cutting, 3 orders done"
    )
    await plant.emulated.broker.stop()
    plant.submit(DURING)  # the factory cannot tell any cell now: they go once it is back
    # The cells go on working without the broker; their reports wait in their mailboxes.
    known = plant.cells_done()
    await plant.wait_for(
        lambda: len(plant.cells_done() - known) >= 2, "cells finish orders while the broker is away"
    )
    await plant.emulated.broker.start()
    await plant.finish()
    plant.check_made_once()


@pytest.mark.timeout(240)  # beyond the plant's own deadlines: they say more
async def test_the_factory_controller_killed_and_restarted(plant: Plant) -> None:
    plant.submit(FIRST)
    await plant.wait_for(
        lambda: len(plant.done()) >= 3 and plant.cutting(), "a cell cutting, 3 orders done"
    )
    await plant.kill("factory")
    plant.submit(DURING)  # in the store, for the factory to send once it is back
    # The cells go on, and their reports wait at the broker for the factory's session.
    known = plant.cells_done()
    await plant.wait_for(
        lambda: len(plant.cells_done() - known) >= 2,
        "cells finish orders while the factory is away",
    )
    assert {o.id for o in plant.store.orders() if o.cell is None} >= {o for o, _, _ in DURING}
    await plant.start("factory")
    await plant.finish()
    plant.check_made_once()


# -- the broker's ACLs, with the credentials the plant hands out -------------------------------
