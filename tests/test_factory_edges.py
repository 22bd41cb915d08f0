"""The factory's edges: the broker's ACLs with the credentials ``EmulatedFactory`` hands
out; malformed states, reports and orders, which stop neither the factory nor a cell (over the
broker, and as hypothesis properties); and the factory's command line (an unknown part type, a
priority too large, a second ``run``, a broken factory.toml, ``cancel`` of an order queued, at
a cell or started there, ``run --until-idle`` with an order no cell makes). The plant is
tests/factory_plant.py; the cancel's parts without a broker are in tests/test_factory_cancel.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import stat
import subprocess
import tempfile
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from rich.console import Console

from cellctl.errors import UsageError
from cellctl.factory.cancel import local_user
from cellctl.factory.config import FactoryConfig
from cellctl.factory.controller import IGNORED_TOLD, FactoryController
from cellctl.factory.dispatch import choose
from cellctl.factory.emulated import EmulatedFactory
from cellctl.factory.store import FINAL_STATES, OPEN_STATES, FactoryStore
from cellctl.mailbox import REPORT_KINDS, open_mailbox
from cellctl.mailbox.mqtt import read_credentials
from cellctl.mailbox.wire import OrderMessage, WireError, parse_to_cell
from cellctl.service.audit import AuditLog
from cellctl.testing.rig import TIME_SCALE, cli
from cellctl.ui.factory_cli import cells_table
from tests.factory_plant import CLI_S, PART_TYPES, WAIT_S, Plant

from .conftest import CELLCTL


@contextlib.asynccontextmanager
async def logged_in(port: int, credentials: Path) -> AsyncIterator[aiomqtt.Client]:
    username, password = read_credentials(credentials)
    async with aiomqtt.Client(
        "127.0.0.1", port, username=username, password=password, timeout=5
    ) as client:
        yield client


async def first_message(client: aiomqtt.Client) -> aiomqtt.Message:
    async with asyncio.timeout(10):
        return await anext(aiter(client.messages))


async def publish_forbidden(client: aiomqtt.Client, topic: str, payload: bytes) -> None:
    # Mosquitto drops a forbidden publish without a word (MQTT 3.1.1): it simply never arrives.
    with contextlib.suppress(aiomqtt.MqttError):
        await client.publish(topic, payload, qos=1, retain=True)


async def test_a_cell_cannot_order_for_or_speak_for_or_listen_to_another_cell(
    tmp_path: Path,
) -> None:
    """What tests/test_broker.py does not cover: a cell's own credentials file, as
    EmulatedFactory writes it into the cell directory, cannot give another cell orders,
    cannot post another cell's state or status (retained: what the factory dispatches on),
    and reads nothing but its own orders, even with a wildcard."""
    async with EmulatedFactory(tmp_path / "plant", cells=2, time_scale=TIME_SCALE) as plant:
        port = plant.broker.port
        files = {
            name: d / "mqtt.toml" for name, d in zip(plant.names, plant.cell_dirs, strict=True)
        }
        files["factory"] = plant.directory / "factory.credentials"
        for path in files.values():
            assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
        assert {read_credentials(p)[0] for p in files.values()} == {"cell1", "cell2", "factory"}
        # One cell's password is not another's.
        with pytest.raises(aiomqtt.MqttError):
            password = read_credentials(files["cell1"])[1]
            async with aiomqtt.Client(
                "127.0.0.1", port, username="cell2", password=password, timeout=5
            ):
                pass
        async with (
            logged_in(port, files["cell1"]) as cell1,
            logged_in(port, files["cell2"]) as cell2,
            logged_in(port, files["factory"]) as factory,
        ):
            # cell1 cannot give cell2 an order: cell2 gets the factory's only.
            await cell2.subscribe("cellctl/cell2/orders", qos=1)
            forged = b'{"v":1,"id":"forged","part_type":"wax-robot-base","qty":5}'
            await publish_forbidden(cell1, "cellctl/cell2/orders", forged)
            real = b'{"v":1,"id":"real","part_type":"wax-robot-base","qty":1}'
            await factory.publish("cellctl/cell2/orders", real, qos=1)
            assert (await first_message(cell2)).payload == real
            # cell1 cannot speak for cell2 (its state says it is idle, its status offline).
            await factory.subscribe("cellctl/cell2/state", qos=1)
            await factory.subscribe("cellctl/cell2/status", qos=1)
            await publish_forbidden(cell1, "cellctl/cell2/state", b'{"v":1,"cell":"cell2"}')
            await publish_forbidden(cell1, "cellctl/cell2/status", b"offline")
            await cell2.publish("cellctl/cell2/status", b"online", qos=1, retain=True)
            message = await first_message(factory)
            assert (message.topic.value, message.payload) == ("cellctl/cell2/status", b"online")
            # cell1 reads nothing of cell2's, not even with a wildcard: only its own orders.
            await cell1.subscribe("cellctl/#", qos=1)
            await cell2.publish("cellctl/cell2/reports", b'{"v":1,"seq":1}', qos=1)
            await cell2.publish("cellctl/cell2/state", b'{"v":1,"cell":"cell2"}', qos=1)
            await factory.publish("cellctl/cell2/orders", b'{"v":1,"id":"theirs"}', qos=1)
            await factory.publish("cellctl/cell1/orders", b'{"v":1,"id":"mine"}', qos=1)
            message = await first_message(cell1)
            assert (message.topic.value, message.payload) == (
                "cellctl/cell1/orders",
                b'{"v":1,"id":"mine"}',
            )
        # Nothing forged was retained: a newcomer gets no state (it subscribes to that first:
        # retained messages come in the order of the subscriptions), and cell2's own status.
        async with logged_in(port, files["factory"]) as late:
            await late.subscribe("cellctl/cell2/state", qos=1)
            await late.subscribe("cellctl/cell2/status", qos=1)
            message = await first_message(late)
            assert (message.topic.value, message.payload) == ("cellctl/cell2/status", b"online")


#: Messages a cell may send about itself that no cellctl would: JSON of the right version with
#: fields of the wrong kind. The factory says it ignores each, and goes on.
MALFORMED = {
    "reports": [
        {"v": 1, "cell": "cell1", "seq": "7", "kind": "order-done", "order_id": "M1"},
        {"v": 1, "cell": "cell1", "seq": [7], "kind": "order-done", "order_id": "M1"},
        {"v": 1, "cell": "cell1", "seq": 10**6, "kind": "order-accepted", "time": "now"},
        {"v": 1, "cell": "cell1", "seq": 10**6, "kind": "order-rejected", "data": [True]},
    ],
    "state": [
        {"v": 1, "cell": "cell1", "time": "now"},
        {"v": 1, "cell": "cell1", "part_types": ["wax-robot-base"]},
        {"v": 1, "cell": "cell1", "part_types": {"wax-robot-base": 1.0}},
        {"v": 1, "cell": "cell1", "part_types": {"wax-robot-base": {"bound_s": "1"}}},
        {"v": 1, "cell": "cell1", "part_types": {}, "finish_estimate_s": "soon"},
        {"v": 1, "cell": "cell1", "part_types": {}, "orders_open": "none"},
        {"v": 1, "cell": "cell1", "part_types": {}, "machines": ["robot"]},
    ],
}


#: Orders no factory of cellctl sends (its store refuses them): numbers SQLite cannot keep.
POISONED_ORDERS = [
    {"v": 1, "id": "X1", "part_type": "wax-robot-base", "qty": 1, "priority": 2**70},
    {"v": 1, "id": "X2", "part_type": "wax-robot-base", "qty": 2**64},
    {"v": 1, "id": "X3", "part_type": "wax-robot-base", "qty": 1, "expires": float("nan")},
]


async def test_malformed_messages_stop_neither_the_factory_nor_a_cell(tmp_path: Path) -> None:
    async with Plant(tmp_path / "plant", cells=1) as plant:
        await plant.start_all()
        before = len(plant.store.events(limit=10_000))
        port = plant.emulated.broker.port
        # The broker keeps one session a user: cell1's controller steps aside meanwhile.
        await plant.stop("cell1")
        async with logged_in(port, plant.cell_dir("cell1") / "mqtt.toml") as cell1:
            for topic, payloads in MALFORMED.items():
                for payload in payloads:
                    await cell1.publish(f"cellctl/cell1/{topic}", json.dumps(payload), qos=1)
        count = sum(len(p) for p in MALFORMED.values())

        told = min(count, IGNORED_TOLD)  # in full; the rest counted once the window ends

        def ignored() -> list[str]:
            events = plant.store.events(limit=10_000)[before:]
            return [e.text for e in events if e.cell == "cell1" and "ignored" in e.text]

        def all_told() -> bool:
            said = ignored()
            counted = count == told or any("more messages ignored" in t for t in said)
            return counted and sum("message ignored (" in t for t in said) >= told

        await plant.wait_for(all_told, "the factory ignores each of them")
        said = ignored()
        assert sum("message ignored (" in t for t in said) == told, said
        if count > told:
            assert any(t.startswith(f"cell1: {count - told} more messages ignored") for t in said)
        await plant.start("cell1")
        await plant.wait_for(
            lambda: plant.store.cells()["cell1"].status == "online", "cell1 online again"
        )
        await plant.stop("factory")
        async with logged_in(port, plant.directory / "factory.credentials") as factory:
            for order in POISONED_ORDERS:
                await factory.publish("cellctl/cell1/orders", json.dumps(order), qos=1)
        log = plant.logs / "cell1.log"
        await plant.wait_for(
            lambda: log.read_text().count("order refused") == len(POISONED_ORDERS),
            "the cell refuses each poisoned order",
        )
        await plant.start("factory")
        assert plant.mailboxes["cell1"].orders() == []
        # Both still run: the factory knows what the cell makes, and has an order made there.
        plant.submit([("M1", "wax-robot-base", 1)])
        await plant.wait_for(lambda: plant.done() == {"M1"}, "order M1 done")
        assert plant.store.get("M1").done == 1
        assert set(PART_TYPES) <= set(plant.store.cells()["cell1"].part_types)
        assert len(plant.cell("cell1").runs_per_part()) == 1
        code, out = await cellctl("factory", "--dir", str(plant.directory), "cells")
        assert code == 0 and "cell1" in out, out


_JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=6),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=8,
)
_MESSAGE = st.fixed_dictionaries(
    {"v": st.just(1)},
    optional={
        "cell": st.just("cell1") | _JSON,
        "epoch": st.sampled_from(["0123456789abcdef", "fedcba9876543210"]) | _JSON,
        "seq": st.integers(min_value=-2, max_value=2**64) | st.integers(0, 4) | _JSON,
        "kind": st.sampled_from(REPORT_KINDS) | _JSON,
        "withdrawn": st.booleans() | _JSON,
        "order_id": st.sampled_from(["Q", "S", None]) | _JSON,
        "time": _JSON,
        "data": st.fixed_dictionaries({}, optional={"expired": _JSON}) | _JSON,
        "part_types": st.dictionaries(
            st.sampled_from(PART_TYPES),
            st.fixed_dictionaries({}, optional={"bound_s": _JSON}) | _JSON,
            max_size=2,
        )
        | _JSON,
        "machines": st.dictionaries(st.text(max_size=4), _JSON, max_size=2) | _JSON,
        "finish_estimate_s": _JSON,
        "orders_open": _JSON,
        "parts_open": _JSON,
        "paused": _JSON,
    },
)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["state", "reports", "status"]), _MESSAGE | _JSON)))
@example([("state", {"v": 1, "part_types": {"wax-robot-base": 1.0}})])
@example([("reports", {"v": 1, "seq": [7], "kind": "order-done", "order_id": "S"})])
@example([("reports", {"v": 1, "seq": 3, "kind": "order-rejected", "order_id": "S", "data": [1]})])
def test_the_factory_takes_any_message_a_cell_can_send(messages: list[tuple[str, Any]]) -> None:
    """Whatever a cell publishes on its own topics, the factory stores it or ignores it, and
    can go on dispatching and showing its cells (the process test above, for any payload)."""
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        config = FactoryConfig(
            directory, "f", 2.0, 30.0, 0.5, "mqtt://127.0.0.1:1", directory / "c", None,
            {"cell1": "cellctl/cell1"},
        )  # fmt: skip
        with FactoryStore(config.state_path) as store:
            factory = FactoryController(config, store)
            store.submit("wax-robot-base", 1, order_id="Q")
            store.submit("wax-robot-base", 1, order_id="S")
            store.send("S", "cell1", 1e12)
            for topic, payload in messages:
                factory.take(f"cellctl/cell1/{topic}", json.dumps(payload).encode())
            factory.take("cellctl/cell1/status", b"online")
            cells, open_orders = store.cells(), store.orders(OPEN_STATES)
            for order in open_orders:
                choose(order, cells, open_orders)
            Console(file=io.StringIO()).print(cells_table(store, config))
            assert {o.state for o in store.orders()} <= {*OPEN_STATES, *FINAL_STATES}


@settings(max_examples=80, deadline=None)
@given(
    st.fixed_dictionaries(
        {"v": st.just(1), "id": st.text(max_size=4) | _JSON},
        optional={
            "part_type": st.sampled_from(PART_TYPES) | _JSON,
            "qty": st.integers() | _JSON,
            "priority": st.integers() | _JSON,
            "expires": _JSON,
        },
    )
    | _JSON
)
@example({"v": 1, "id": "A", "part_type": "wax-robot-base", "qty": 1, "priority": 2**70})
def test_a_cell_takes_or_refuses_any_order_message(order: Any) -> None:
    """An order message either goes into the cell's mailbox or is refused with a UsageError."""
    with tempfile.TemporaryDirectory() as tmp, open_mailbox(Path(tmp)) as mailbox:
        try:
            message = parse_to_cell(json.dumps(order).encode())
            assert isinstance(message, OrderMessage)
            mailbox.post_order(message.part_type, message.qty, message.priority, message.id)
        except (UsageError, WireError):
            return
        assert [o.id for o in mailbox.orders()] == [order["id"]]


# -- the command line ------------------------------------------------------------------------


async def cellctl(*args: str) -> tuple[int, str]:
    """``cellctl ARGS`` in its own process (the plant's emulators keep running meanwhile):
    its exit code and what it printed."""
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, *args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT
    )
    try:
        async with asyncio.timeout(60):
            out, _ = await proc.communicate()
    except TimeoutError:
        proc.kill()
        await proc.wait()
        raise AssertionError(f"cellctl {' '.join(args)} did not return within 60 s") from None
    assert proc.returncode is not None
    return proc.returncode, out.decode(errors="replace")


async def test_the_factory_command_line_on_a_running_plant(tmp_path: Path) -> None:
    async with Plant(tmp_path / "plant", cells=1) as plant:
        await plant.start_all()
        where = ["factory", "--dir", str(plant.directory)]
        # A part type no cell makes, once the cells have said what they make.
        code, out = await cellctl(*where, "submit", "wax-robot-arm", "--qty", "2")
        assert code != 0, out
        assert "wax-robot-arm" in out and all(t in out for t in PART_TYPES), out
        assert "Traceback" not in out and plant.store.orders() == []
        # A priority beyond what the store can keep.
        code, out = await cellctl(*where, "submit", PART_TYPES[0], "--priority", str(2**70))
        assert code != 0 and "priority" in out and "Traceback" not in out, out
        assert plant.store.orders() == []
        # A second controller for the same directory, while the first runs.
        code, out = await cellctl(*where, "run", "--no-live")
        assert code != 0, out
        assert "already run by" in out and f"pid {plant.procs['factory'].pid}" in out, out
        assert plant.procs["factory"].returncode is None
        # A good order from the command line is made.
        code, out = await cellctl(
            *where, "submit", "wax-toy-mill-table", "--qty", "2", "--id", "C1"
        )
        assert code == 0, out
        await plant.wait_for(lambda: plant.done() == {"C1"}, "order C1 done")
        code, out = await cellctl(*where, "orders")
        assert code == 0 and "C1" in out and "done" in out, out
        assert plant.store.get("C1").done == 2
        assert len(plant.cell("cell1").runs_per_part()) == 2
        # The same id again: the same order is a retry; another one is refused, unchanged.
        code, out = await cellctl(
            *where, "submit", "wax-toy-mill-table", "--qty", "2", "--id", "C1"
        )
        assert code == 0 and "already submitted (unchanged)" in out, out
        code, out = await cellctl(*where, "submit", "wax-robot-base", "--id", "C1")
        said = " ".join(out.split())
        assert code == 2 and "order C1 was submitted before as 2 × wax-toy-mill-table" in said
        assert plant.store.get("C1").part_type == "wax-toy-mill-table"
        await cancels(plant)
        await until_idle_ends_when_nothing_more_can_happen(plant)


async def in_process(plant: Plant, *args: str) -> tuple[int, str]:
    """``cellctl ARGS`` through click in a worker thread (no process more to start): its exit
    code and what it printed; ``factory`` commands are given the plant's directory."""
    if args[0] == "factory":
        args = ("factory", "--dir", str(plant.directory), *args[1:])
    try:
        async with asyncio.timeout(CLI_S):
            result = await cli(plant.cell_dir("cell1"), *args)
    except TimeoutError:
        raise AssertionError(f"cellctl {' '.join(args)}: no answer\n{plant.describe()}") from None
    return result.exit_code, result.output


async def cancels(plant: Plant) -> None:
    """``cellctl factory cancel``: an unknown or a done order refused before anything is
    sent; a queued order cancelled at once; an order at the (paused) cell cancelling while
    the factory is away, asked twice and sent once it is back, then cancelled by the cell's
    own cancel, nothing of it made; an order that has started refused by the cell, and
    made."""
    user, store, mailbox = local_user(), plant.store, plant.mailboxes["cell1"]
    journal = plant.journals["cell1"]

    async def ok(*args: str) -> str:
        code, out = await in_process(plant, *args)
        assert code == 0, f"{args}: {out}\n{plant.describe()}"
        return out

    events = len(store.events(limit=10_000))
    code, out = await in_process(plant, "factory", "cancel", "NOPE")
    assert code != 0 and "no order 'NOPE' in the factory" in out, out
    code, out = await in_process(plant, "factory", "cancel", "C1")
    assert code != 0 and "order C1 is done: there is nothing to cancel" in out, out
    assert len(store.events(limit=10_000)) == events and store.get("C1").cancel_asked is None
    # K1 at the cell, not started: a paused cell takes orders and starts nothing.
    await ok("pause")
    plant.submit([("K1", PART_TYPES[0], 2)])
    await plant.wait_for(lambda: store.get("K1").state == "accepted", "K1 accepted by cell1")
    await plant.stop("factory")
    plant.submit([("Q1", PART_TYPES[1], 1)])  # at no cell: the factory is away
    out = await ok("factory", "cancel", "Q1", "--reason", "ordered twice")
    assert "order Q1 cancelled (it was at no cell)" in out, out
    q1 = store.get("Q1")
    assert (q1.state, q1.note) == ("cancelled", f"cancelled by {user}: ordered twice")
    out = await ok("factory", "cancel", "K1", "--reason", "wrong material")
    assert "order K1: cancelling at cell1" in out, out
    out = await ok("factory", "cancel", "K1")
    assert "a cancel is already on its way to cell1" in out and "nothing sent again" in out, out
    (row,) = [line for line in (await ok("factory", "orders")).splitlines() if "K1" in line]
    assert "cancelling" in row, row
    await plant.start("factory")
    await plant.wait_for(lambda: store.get("K1").state == "cancelled", "K1 cancelled by cell1")
    k1 = store.get("K1")
    assert k1.note == f"order K1 cancelled (asked by {user}: wrong material)", k1
    assert mailbox.get_order("K1").state == "cancelled"
    assert [p.status for p in journal.parts(order_id="K1")] == ["cancelled"] * 2
    asked = [e.text for e in store.events(limit=10_000) if e.order_id == "K1"]
    assert (
        asked.count(f"order K1: cancel asked by {user}: wrong material; cell1 is to cancel it") == 1
    )
    with AuditLog(plant.cell_dir("cell1")) as audit:
        who = [(e.who, e.method, e.result) for e in audit.entries()]
    assert (f"factory:{user}", "orders.cancel", "ok") in who, who
    # R1 has started: the cell's own cancel refuses it, and R1 is made.
    await ok("resume")
    plant.submit([("R1", PART_TYPES[0], 3)])
    await plant.wait_for(lambda: journal.open_steps(), "a step of R1 under way at cell1")
    await ok("pause")
    await plant.wait_for(lambda: store.get("R1").state == "in-progress", "R1 in progress")
    out = await ok("factory", "cancel", "R1")
    assert "it has started there" in out, out
    await plant.wait_for(lambda: store.get("R1").cancel_asked is None, "cell1 refuses to cancel R1")
    r1 = store.get("R1")
    assert r1.shown_state == "in-progress" and "cell1 did not cancel it" in r1.note, r1
    assert "started" in r1.note, r1  # in the cell's words: it cannot be cancelled
    await ok("resume")
    await plant.wait_for(lambda: store.get("R1").state == "done", "R1 done")
    # Made: C1's two parts and R1's three; nothing of K1 (cancelled) or Q1.
    assert len(plant.cell("cell1").runs_per_part()) == 5, plant.describe()
    assert [p.status for p in journal.parts(order_id="K1")] == ["cancelled"] * 2


async def until_idle_ends_when_nothing_more_can_happen(plant: Plant) -> None:
    """``run --until-idle`` with an order no cell makes (submitted before the cells said
    what they make: the store takes it) and one for a cell that is offline: the first fails,
    saying why; the second waits for its cell, and once it is made the run returns."""
    store = plant.store
    await plant.stop("cell1")
    await plant.wait_for(lambda: store.cells()["cell1"].status == "offline", "cell1 offline")
    await plant.stop("factory")
    plant.submit([("U1", "wax-robot-arm", 1), ("W1", PART_TYPES[0], 1)])
    proc = await plant.start("factory", "--until-idle")
    await plant.wait_for(lambda: store.get("U1").state == "failed", "U1 failed")
    made = ", ".join(sorted(plant.part_types("cell1")))
    assert store.get("U1").note == f"no cell makes wax-robot-arm (the cells make: {made})"
    w1 = store.get("W1")
    assert (w1.state, w1.note) == (
        "queued",
        f"waiting for a cell that makes {PART_TYPES[0]} to come online (cell1)",
    ), plant.describe()
    assert proc.returncode is None  # W1 waits for cell1: the run goes on
    await plant.start("cell1")
    try:
        async with asyncio.timeout(WAIT_S):
            await proc.wait()
    except TimeoutError:
        raise AssertionError(f"--until-idle did not return\n{plant.describe()}") from None
    plant.procs.pop("factory")
    assert proc.returncode == 0, plant.describe()
    assert store.get("W1").state == "done"
    # What it keeps of the cell is its state after the last part: none open.
    assert store.cells()["cell1"].state.get("parts_open") == 0, plant.describe()
    log = (plant.logs / "factory.log").read_text()
    assert f"order U1 failed: no cell makes wax-robot-arm (the cells make: {made})" in log, log
    assert "order W1 waits: waiting for a cell that makes" in log, log


BROKEN = {
    "not TOML": "[factory\nname = 1\n",
    "no broker": '[cells.cell1]\nprefix = "cellctl/cell1"\n',
    "a bad url": '[broker]\nurl = "http://x"\ncredentials = "c"\n[cells.a]\nprefix = "p"\n',
}


@pytest.mark.parametrize("broken", list(BROKEN))
def test_a_broken_factory_toml_is_one_line(tmp_path: Path, broken: str) -> None:
    (tmp_path / "factory.toml").write_text(BROKEN[broken])
    for command in (["run", "--no-live"], ["submit", "wax-robot-base"], ["orders"]):
        done = subprocess.run(
            [*CELLCTL, "factory", "--dir", str(tmp_path), *command],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode != 0, (command, done.stdout)
        lines = (done.stdout + done.stderr).strip().splitlines()
        assert len(lines) == 1, (command, lines)
        assert "factory.toml" in lines[0] and "Traceback" not in lines[0], lines
    assert not (tmp_path / "state").exists()


def test_a_cell_flooding_bad_messages_is_told_in_a_few_lines() -> None:
    """Thousands of malformed messages from one cell's credentials: the first few logged in
    full, the rest counted in one line once the window ends, not a line (and a row of the
    store's events) each."""
    from cellctl.clock import current_clock, run_virtual
    from cellctl.factory.controller import IGNORED_TOLD, IGNORED_WINDOW_S

    async def flood(directory: Path) -> list[str]:
        config = FactoryConfig(
            directory, "f", 2.0, 30.0, 0.5, "mqtt://127.0.0.1:1", directory / "c", None,
            {"cell1": "cellctl/cell1", "cell2": "cellctl/cell2"},
        )  # fmt: skip
        with FactoryStore(config.state_path) as store:
            factory = FactoryController(config, store)
            for _ in range(3000):
                factory.take("cellctl/cell1/reports", b"not json")
            factory.take("cellctl/cell2/reports", b"not json either")  # another cell's own
            await current_clock().sleep(IGNORED_WINDOW_S)
            factory.take("cellctl/cell1/reports", b"again")  # a new window: told in full
            return [e.text for e in store.events(limit=100_000)]

    with tempfile.TemporaryDirectory() as tmp:
        said = run_virtual(flood(Path(tmp)), start=0.0)
    cell1 = [t for t in said if t.startswith("cell1:")]
    ignored = [t for t in cell1 if "a reports message ignored" in t]
    assert len(ignored) == IGNORED_TOLD + 1, cell1
    counted = [t for t in cell1 if "more messages ignored" in t]
    assert counted == [
        f"cell1: {3000 - IGNORED_TOLD} more messages ignored in {IGNORED_WINDOW_S:.0f} s "
        f"(the first {IGNORED_TOLD} told above)"
    ], cell1
    assert any(t.startswith("cell2: a reports message ignored") for t in said), said
