"""An order's due time from the factory: ``cellctl factory submit --due WHEN`` takes the forms
and gives the refusals of the cell's ``cellctl submit --due``, keeps the time in the factory's
store (a store from before due times gains the column), shows it in ``cellctl factory
orders`` (LATE once past), and sends it with the order, so the cell's ``cellctl orders``
shows it. The command line without a broker first; then over the plant of
tests/factory_plant.py (a real Mosquitto, a cell's ``cellctl run``, ``cellctl factory run``).
The wire's ``due`` (left out when there is none, an older peer's order without it read) is in
tests/test_order_due.py."""

from __future__ import annotations

import asyncio
import json
import re
from datetime import datetime
from pathlib import Path
from typing import Any

from click.testing import CliRunner

from cellctl.clock import current_clock
from cellctl.factory.config import load_factory
from cellctl.factory.store import SCHEMA, FactoryStore
from cellctl.plan.when import resolve_when
from cellctl.testing.rig import cli
from cellctl.ui.cli import main
from tests.factory_plant import CLI_S, PART_TYPES, Plant
from tests.test_factory_cancel import old_store
from tests.test_factory_cli_words import FACTORY_TOML

BASE, TABLE = PART_TYPES
#: A due time already past: the order is late from the start.
PAST = "2020-01-06T08:00"


def factory_dir(tmp_path: Path) -> Path:
    directory = tmp_path / "factory"
    directory.mkdir()
    (directory / "factory.toml").write_text(FACTORY_TOML)
    return directory


def factory(directory: Path, *args: str, expect: int = 0) -> str:
    """``cellctl factory --dir DIRECTORY ARGS`` through click: what it printed."""
    result = CliRunner().invoke(main, ["factory", "--dir", str(directory), *args])
    assert result.exit_code == expect, result.output + repr(result.exception)
    return " ".join(result.output.split())


def test_submit_due_is_kept_shown_and_a_retry_must_ask_the_same(tmp_path: Path) -> None:
    directory = factory_dir(tmp_path)
    said = factory(directory, "submit", BASE, "--qty", "2", "--id", "D1", "--due", "FRI 18:00")
    with FactoryStore(load_factory(directory).state_path) as store:
        due = store.get("D1").due
        assert due is not None and store.get("D1").part_type == BASE
        events = [e.text for e in store.events()]
    # The next Friday 18:00 on this host's clock, as the cell's --due and plan --until read it.
    assert datetime.fromtimestamp(due).strftime("%a %H:%M") == "Fri 18:00"
    assert 0 < due - current_clock().now() <= 7 * 86400
    shown = datetime.fromtimestamp(due).strftime("%Y-%m-%d 18:00:00")
    assert said == f"order D1 submitted: 2 x {BASE}, due Fri {shown}", said
    assert f"order D1 submitted: 2 x {BASE}, due Fri {shown}" in events
    # The same order again changes nothing; another due time for the id is another order.
    again = factory(directory, "submit", BASE, "--qty", "2", "--id", "D1", "--due", "FRI 18:00")
    assert again.startswith("order D1 already submitted (unchanged)"), again
    other = factory(directory, "submit", BASE, "--qty", "2", "--id", "D1", expect=2)
    assert f"order D1 was submitted before as 2 × {BASE}, priority 0, due Fri {shown}, not " in (
        other
    ), other
    assert "give this order another --id" in other
    # One past already is taken, and said to be late; one without a due time is as before.
    late = factory(directory, "submit", TABLE, "--id", "D2", "--due", PAST)
    assert late.endswith("(already past: the order is late)"), late
    plain = factory(directory, "submit", TABLE, "--id", "D3")
    assert plain == f"order D3 submitted: 1 x {TABLE}", plain
    rows = {row.split()[0]: row for row in orders_lines(directory) if row.startswith("D")}
    assert shown in rows["D1"] and "LATE" not in rows["D1"], rows
    assert "2020-01-06 08:00:00 LATE" in rows["D2"], rows
    assert "LATE" not in rows["D3"] and "2020" not in rows["D3"], rows
    found = {o["id"]: o for o in json.loads(factory(directory, "orders", "--json"))}
    assert (found["D1"]["due"], found["D1"]["late"]) == (due, False)
    assert (found["D2"]["due"], found["D2"]["late"]) == (resolve_when(PAST, 0, due=True), True)
    assert (found["D3"]["due"], found["D3"]["late"]) == (None, False)


def orders_lines(directory: Path) -> list[str]:
    """``cellctl factory orders``, each line's words without the table's rules."""
    result = CliRunner().invoke(main, ["factory", "--dir", str(directory), "orders"])
    assert result.exit_code == 0, result.output
    return [" ".join(re.sub("[│┃]", " ", line).split()) for line in result.output.splitlines()]


def test_a_factory_without_due_times_lists_its_orders_as_before(tmp_path: Path) -> None:
    directory = factory_dir(tmp_path)
    factory(directory, "submit", BASE, "--id", "P1")
    (header,) = [line for line in orders_lines(directory) if line.startswith("order ")]
    assert header.split() == ["order", "part", "qty", "state", "cell", "done", "held", "note"]


def test_a_due_time_it_cannot_read_is_refused_before_anything_is_recorded(
    tmp_path: Path,
) -> None:
    directory = factory_dir(tmp_path)
    for given, words in [
        ("Friday", "--due: time 'Friday': write HH:MM, DAY HH:MM (FRI 18:00) or a date and time"),
        ("25:00", "--due: time '25:00': hours 0-23, minutes 0-59"),
        ("FRY 18:00", "'FRY' is not a day (MON TUE WED THU FRI SAT SUN)"),
        ("9999-01-01T00:00", "an order's due time must be unix seconds from 0 to"),
    ]:
        said = factory(directory, "submit", BASE, "--id", "B1", "--due", given, expect=2)
        assert words in said and "Traceback" not in said, said
    # Not even the store was made: nothing recorded, so nothing can be sent.
    assert not load_factory(directory).state_path.exists()


def test_a_store_from_before_due_times_is_opened_and_kept(tmp_path: Path) -> None:
    path = tmp_path / "factory.db"
    old = SCHEMA.replace(",\n    due REAL\n", "\n")
    assert "due" not in old
    old_store(path, old)
    with FactoryStore(path) as store:
        assert store.get("OLD").due is None
        order, new = store.submit(BASE, 1, order_id="NEW", due=1_800_000_000.0)
        assert new and order.due == 1_800_000_000.0


# -- over the broker -------------------------------------------------------------------------


async def test_a_due_time_from_the_factory_reaches_the_cells_orders(tmp_path: Path) -> None:
    """The cell is paused (it takes orders, starts nothing): what is checked is the orders'
    way, not their parts."""
    async with Plant(tmp_path / "plant", cells=1) as plant:
        await plant.start_all()
        store, mailbox = plant.store, plant.mailboxes["cell1"]

        async def run(*args: str, at: str = "cell1") -> tuple[int, str]:
            if args[0] == "factory":
                args = ("factory", "--dir", str(plant.directory), *args[1:])
            try:
                async with asyncio.timeout(CLI_S):
                    result = await cli(plant.cell_dir(at), *args)
            except TimeoutError:
                raise AssertionError(f"cellctl {args}: no answer\n{plant.describe()}") from None
            return result.exit_code, result.output

        code, out = await run("pause")
        assert code == 0, out
        # A due time it cannot read: refused, nothing recorded, so nothing sent.
        code, out = await run("factory", "submit", BASE, "--id", "BAD", "--due", "FRIDAY 6pm")
        assert code == 2 and "--due: time 'FRIDAY 6pm'" in out, out
        assert store.orders() == []
        for args in (["--id", "D1", "--due", "FRI 18:00"], ["--id", "D2", "--due", PAST]):
            code, out = await run("factory", "submit", BASE, *args)
            assert code == 0, out
        code, out = await run("factory", "submit", TABLE, "--id", "N1")
        assert code == 0, out

        def all_accepted() -> bool:
            return all(store.get(oid).state == "accepted" for oid in ("D1", "D2", "N1"))

        await plant.wait_for(all_accepted, "D1, D2 and N1 accepted by cell1")
        # In the cell's own mailbox, as the factory has them.
        due = {o.id: o.due for o in store.orders()}
        assert due["D1"] is not None and due["D2"] == resolve_when(PAST, 0, due=True)
        assert mailbox.due_times() == {"D1": due["D1"], "D2": due["D2"]}
        assert "BAD" not in {o.id for o in mailbox.orders()}
        # `cellctl orders` at the cell: each due time, LATE for the one past, none for N1.
        code, out = await run("orders", "--json")
        assert code == 0, out
        listed: dict[str, Any] = {o["id"]: o for o in json.loads(out)}
        assert {k: (v["due"], v["late"]) for k, v in listed.items()} == {
            "D1": (due["D1"], False),
            "D2": (due["D2"], True),
            "N1": (None, False),
        }
        code, out = await run("orders")
        assert code == 0, out
        d1 = datetime.fromtimestamp(due["D1"]).strftime("%Y-%m-%d %H:%M:%S")
        assert d1.endswith("18:00:00") and d1 in out, out
        assert re.search(r"2020-01-06 08:00:00\s+LATE", out), out
        # And the factory's own listing.
        code, out = await run("factory", "orders")
        assert code == 0, out
        assert d1 in out and re.search(r"2020-01-06[\s│]+08:00:00[\s│]+LATE", out), out
