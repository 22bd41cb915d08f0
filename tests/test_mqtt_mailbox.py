"""The cell's mailbox on a real Mosquitto: the broker's passwords and ACLs, orders in and
reports out through the emulated cell, a repeated order id, the retained state and status, a
broker restarted mid-batch, and the last will when ``cellctl run`` is killed."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import aiomqtt
import pytest

from cellctl.errors import UsageError
from cellctl.factory.broker import FACTORY_USER, MosquittoBroker
from cellctl.mailbox import open_mailbox
from cellctl.mailbox.mqtt import MqttBridge, MqttSettings, read_credentials
from cellctl.mailbox.wire import AskMessage
from cellctl.testing.rig import CellRig

from .conftest import emulated_cell_process

CELLS = [("cell1", "cellctl/cell1"), ("cell2", "cellctl/cell2")]


def client(broker: MosquittoBroker, user: str, **more: Any) -> aiomqtt.Client:
    username, password = read_credentials(broker.credentials(user))
    return aiomqtt.Client(
        "127.0.0.1", broker.port, username=username, password=password, timeout=5, **more
    )


async def next_message(c: aiomqtt.Client, timeout: float = 20.0) -> aiomqtt.Message:
    async with asyncio.timeout(timeout):
        return await anext(aiter(c.messages))


async def next_answer(c: aiomqtt.Client) -> dict[str, Any]:
    """The next report that answers an order (other reports, e.g. an alarm, are skipped)."""
    while True:
        report: dict[str, Any] = json.loads((await next_message(c)).payload)  # type: ignore[arg-type]
        if report["kind"] in ("order-accepted", "order-rejected"):
            return report


async def nothing_arrives(c: aiomqtt.Client, within: float = 1.0) -> bool:
    try:
        await next_message(c, within)
    except TimeoutError:
        return True
    return False


@pytest.fixture
async def broker(tmp_path: Path) -> AsyncIterator[MosquittoBroker]:
    async with MosquittoBroker(tmp_path / "broker", CELLS) as b:
        yield b


async def test_a_wrong_password_and_another_cells_topics_are_refused(
    broker: MosquittoBroker,
) -> None:
    for path in [broker.credentials(u) for u in ("factory", "cell1", "cell2")]:
        assert path.stat().st_mode & 0o777 == 0o600
    with pytest.raises(aiomqtt.MqttError, match=r"[Nn]ot authori[sz]ed"):
        async with aiomqtt.Client("127.0.0.1", broker.port, username="cell1", password="x"):
            pass
    async with client(broker, "cell1") as cell1, client(broker, FACTORY_USER) as factory:
        # cell1 cannot read cell2's orders ...
        await cell1.subscribe("cellctl/cell2/orders", qos=1)
        await factory.publish("cellctl/cell2/orders", b"{}", qos=1)
        assert await nothing_arrives(cell1)
        # ... nor post cell2's reports; its own arrive.
        await factory.subscribe("cellctl/+/reports", qos=1)
        await cell1.publish("cellctl/cell2/reports", b"forged", qos=1)
        await cell1.publish("cellctl/cell1/reports", b"mine", qos=1)
        message = await next_message(factory)
        assert message.topic.value == "cellctl/cell1/reports" and message.payload == b"mine"


async def test_credentials_that_others_may_read_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('username = "a"\npassword = "b"\n')
    path.chmod(0o644)
    with pytest.raises(UsageError, match="chmod 600"):
        read_credentials(path)


async def test_orders_in_reports_out_a_repeated_id_and_the_retained_state(
    tmp_path: Path, broker: MosquittoBroker
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        controller = await rig.start_controller()
        settings = MqttSettings.load(f"{broker.url}/cellctl/cell1", broker.credentials("cell1"))
        with open_mailbox(rig.directory) as mailbox:
            bridge = MqttBridge(settings, controller, mailbox, rig.journal)
            task = asyncio.create_task(bridge.run())
            # The cell's session is new: an order published before it subscribed is not its.
            async with asyncio.timeout(20):
                await bridge.connected.wait()
            async with client(broker, FACTORY_USER, identifier="f", clean_session=False) as f:
                await f.subscribe("cellctl/cell1/reports", qos=1)
                # Due in a day: the cell's mailbox keeps it (its plans say on time or late).
                due = time.time() + 86400
                order = {"v": 1, "id": "F1", "part_type": "wax-robot-base", "qty": 1, "due": due}
                await f.publish("cellctl/cell1/orders", json.dumps(order), qos=1)
                seen: list[dict[str, Any]] = []
                while not any(r["kind"] == "order-done" for r in seen):
                    seen.append(json.loads((await next_message(f)).payload))  # type: ignore[arg-type]
                assert [r["seq"] for r in seen] == list(range(1, len(seen) + 1))
                accepted = [r for r in seen if r["kind"] == "order-accepted"]
                assert accepted[0]["order_id"] == "F1"
                assert mailbox.due_times() == {"F1": due}
                assert accepted[0]["cell"] == controller.config.name
                # The same id again: no new order; the answer it had is sent again.
                await f.publish("cellctl/cell1/orders", json.dumps(order), qos=1)
                assert await next_answer(f) == accepted[0]
                assert [o.id for o in mailbox.orders()] == ["F1"]
                # The factory asks for every report after 0 again: each comes again, as it was.
                ask = AskMessage(ask="reports", epoch=mailbox.epoch, after=0)
                await f.publish("cellctl/cell1/orders", ask.model_dump_json(), qos=1)
                again = [json.loads((await next_message(f)).payload) for _ in seen]  # type: ignore[arg-type]
                assert again == seen
                assert {r["epoch"] for r in again} == {mailbox.epoch}
                # Past its expiry (the factory gave it to another cell): refused, not made.
                late = {**order, "id": "F0", "expires": time.time() - 1}
                await f.publish("cellctl/cell1/orders", json.dumps(late), qos=1)
                refused = await next_answer(f)
                assert refused["kind"] == "order-rejected" and "expired" in refused["text"]
                assert [o.id for o in mailbox.orders()] == ["F1"]
            # A newcomer reads the retained state and status.
            retained: dict[str, Any] = {}
            async with client(broker, FACTORY_USER) as late:
                await late.subscribe("cellctl/cell1/state", qos=1)
                await late.subscribe("cellctl/cell1/status", qos=1)
                while len(retained) < 2:
                    message = await next_message(late)
                    retained[message.topic.value.rpartition("/")[2]] = message.payload
            assert retained["status"] == b"online"
            state = json.loads(retained["state"])
            assert state["v"] == 1 and state["cell"] == controller.config.name
            assert set(state["part_types"]) == set(controller.config.parts)
            assert state["part_types"]["wax-robot-base"]["bound_s"] > 0
            assert {"robot", "cnc1", "cnc2"} <= set(state["machines"])
            assert "finish_estimate_s" in state and "orders_open" in state
            await bridge.stop()
            async with asyncio.timeout(10):
                await task
        await rig.stop_controller()


async def test_broker_restart_mid_batch_and_the_last_will(
    tmp_path: Path, broker: MosquittoBroker
) -> None:
    stack = contextlib.ExitStack()
    cell = stack.enter_context(emulated_cell_process(tmp_path / "cell", "1000"))
    run: subprocess.Popen[bytes] | None = None
    try:
        (cell / "mqtt.toml").write_bytes(broker.credentials("cell1").read_bytes())
        os.chmod(cell / "mqtt.toml", 0o600)
        url = f"{broker.url}/cellctl/cell1"
        with (cell / "cell.toml").open("a") as toml:
            toml.write(f'\n[mailbox]\nurl = "{url}"\ncredentials = "mqtt.toml"\n')
        log = (tmp_path / "run.log").open("wb")
        run = subprocess.Popen(  # noqa: ASYNC220
            [sys.executable, "-m", "cellctl", "--cell", str(cell), "run", "--no-live"],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        # The factory's persistent session takes every report, also while the broker is
        # away (the broker binds a session to its user: one factory client at a time).
        seqs: list[int] = []
        done: set[str] = set()
        epochs: set[str] = set()

        async def follow(f: aiomqtt.Client, until: Callable[[], bool]) -> None:
            while not until():
                message = await next_message(f, 60)
                if message.topic.value.endswith("/reports"):
                    report = json.loads(message.payload)  # type: ignore[arg-type]
                    seqs.append(report["seq"])
                    epochs.add(report["epoch"])
                    if report["kind"] == "order-done":
                        done.add(report["order_id"])

        async with client(broker, FACTORY_USER, identifier="f", clean_session=False) as f:
            await f.subscribe("cellctl/cell1/reports", qos=1)
            await f.subscribe("cellctl/cell1/status", qos=1)
            while (await next_message(f, 30)).payload != b"online":
                pass
            for oid in ("F1", "F2"):
                order = {"v": 1, "id": oid, "part_type": "wax-robot-base", "qty": 2}
                await f.publish("cellctl/cell1/orders", json.dumps(order), qos=1)
            await follow(f, lambda: bool(seqs))
        # The broker goes away mid-batch and comes back; the cell reconnects by itself.
        await broker.restart()
        async with client(broker, FACTORY_USER, identifier="f", clean_session=False) as f:
            await follow(f, lambda: done == {"F1", "F2"})
            # A report the broker had taken but lost in its restart leaves a gap: the factory
            # asks for what follows its last report in order, and the cell sends it again.
            missing = sorted(set(range(1, max(seqs) + 1)) - set(seqs))
            if missing:
                (epoch,) = epochs
                ask = AskMessage(ask="reports", epoch=epoch, after=missing[0] - 1)
                await f.publish("cellctl/cell1/orders", ask.model_dump_json(), qos=1)
                await follow(f, lambda: set(range(1, max(seqs) + 1)) <= set(seqs))
        # Every report arrived, none lost for good across the broker's restart.
        assert sorted(set(seqs)) == list(range(1, max(seqs) + 1)), seqs
        assert run.poll() is None
        run.send_signal(signal.SIGKILL)
        run.wait(10)
        async with client(broker, FACTORY_USER) as g:
            await g.subscribe("cellctl/cell1/status", qos=1)
            while (await next_message(g, 30)).payload != b"offline":
                pass
    finally:
        if run is not None and run.poll() is None:
            run.kill()
        stack.close()
