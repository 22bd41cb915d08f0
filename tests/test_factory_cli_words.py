"""The factory's command line in the user's words: what ``cellctl factory orders`` and the
live view of ``cellctl factory run`` show of a factory with many orders (every order in
``orders``, none dropped past 200; in the live view the open ones first, the latest ended
after them, and how many are left out), ``orders --open`` with none, and ``emulate factory
--help``. The store is the factory's own SQLite file, its orders followed through the reports
a cell sends; the commands run through click."""

from __future__ import annotations

import io
import json
import time
from pathlib import Path

from click.testing import CliRunner
from rich.console import Console

from cellctl.factory.config import load_factory
from cellctl.factory.store import FactoryStore
from cellctl.mailbox.wire import parse_report
from cellctl.ui.cli import main
from cellctl.ui.factory_cli import LIVE_ORDERS, live_view

FACTORY_TOML = """
[factory]
name = "lab"

[broker]
url = "mqtt://127.0.0.1:1883"
credentials = "factory.credentials"

[cells.cell1]
prefix = "cellctl/cell1"
"""
EPOCH = "0123456789abcdef"
#: 220 orders made, then 10 still open: more than the 200 `orders` once showed.
ENDED, OPEN = 220, 10


def factory_with_orders(directory: Path) -> Path:
    directory.mkdir()
    (directory / "factory.toml").write_text(FACTORY_TOML)
    seq = 0
    with FactoryStore(load_factory(directory).state_path) as store:
        for n in range(1, ENDED + OPEN + 1):
            oid = f"A{n:03d}"
            store.submit("wax-robot-base", 1, order_id=oid)
            if n > ENDED:
                continue
            store.send(oid, "cell1", expires=time.time() + 30)
            for kind in ("order-accepted", "order-done"):
                seq += 1
                fields = {"cell": "cell1", "epoch": EPOCH, "seq": seq, "kind": kind}
                payload = {"v": 1, "text": kind, "time": 1.0, "order_id": oid, **fields}
                store.take_report("cell1", parse_report(json.dumps(payload).encode()))
    return directory


def orders_cli(directory: Path, *args: str) -> str:
    result = CliRunner().invoke(main, ["factory", "--dir", str(directory), "orders", *args])
    assert result.exit_code == 0, result.output
    return result.output


def ids_in(text: str) -> list[str]:
    return [word for line in text.splitlines() for word in line.split() if word[:1] == "A"]


def test_orders_shows_every_order_and_open_the_open_ones(tmp_path: Path) -> None:
    directory = factory_with_orders(tmp_path / "plant")
    every = [f"A{n:03d}" for n in range(1, ENDED + OPEN + 1)]
    assert ids_in(orders_cli(directory)) == every  # the newest too, past 200
    assert ids_in(orders_cli(directory, "--open")) == every[ENDED:]


def test_the_live_view_shows_the_open_orders_first_then_the_latest_and_how_many_more(
    tmp_path: Path,
) -> None:
    directory = factory_with_orders(tmp_path / "plant")
    config = load_factory(directory)
    out = io.StringIO()
    with FactoryStore(config.state_path) as store:
        _, orders, _ = live_view(store, config).renderables  # cells, orders, events
        Console(file=out, width=200, no_color=True).print(orders)
    shown = ids_in(out.getvalue())
    latest = [f"A{n:03d}" for n in range(ENDED, ENDED - (LIVE_ORDERS - OPEN), -1)]
    assert shown == [f"A{n:03d}" for n in range(ENDED + 1, ENDED + OPEN + 1)] + latest
    left = ENDED + OPEN - LIVE_ORDERS
    assert f"… {left} more: cellctl factory --dir {directory} orders" in out.getvalue()


def test_orders_open_says_when_there_is_none(tmp_path: Path) -> None:
    directory = tmp_path / "plant"
    directory.mkdir()
    (directory / "factory.toml").write_text(FACTORY_TOML)
    assert orders_cli(directory, "--open").strip() == "no open orders"
    assert orders_cli(directory).strip() == "no orders"


def test_emulate_factory_help_names_its_option() -> None:
    result = CliRunner().invoke(main, ["emulate", "factory", "--help"])
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert "COUNT" not in said and "--cells N" in said, result.output
