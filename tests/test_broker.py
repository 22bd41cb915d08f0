"""The private Mosquitto broker: passwords, per-cell ACLs, persistence across a restart.

Every check runs against the real /usr/sbin/mosquitto on a free loopback port. "Nothing
arrives" is shown without sleeping: the same subscriber also listens on a topic it may read,
and the message published there after the forbidden one must be the first it gets.
"""

from __future__ import annotations

import asyncio
import os
import stat
import tomllib
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager, suppress
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from cellctl.factory.broker import MosquittoBroker
from cellctl.mailbox.mqttlink import MqttSettings, Reconnect

CELLS = [("cell1", "cellctl/cell1"), ("cell2", "cellctl/cell2")]
DEADLINE_S = 5.0


def login(broker: MosquittoBroker, user: str) -> tuple[str, str]:
    data = tomllib.loads(broker.credentials(user).read_text())
    return data["username"], data["password"]


@asynccontextmanager
async def client(
    broker: MosquittoBroker, user: str, *, client_id: str | None = None, persistent: bool = False
) -> AsyncIterator[aiomqtt.Client]:
    username, password = login(broker, user)
    props = None
    if persistent:
        props = Properties(PacketTypes.CONNECT)
        props.SessionExpiryInterval = 3600
    async with aiomqtt.Client(
        "127.0.0.1",
        broker.port,
        username=username,
        password=password,
        identifier=client_id,
        protocol=aiomqtt.ProtocolVersion.V5,
        clean_start=not persistent,
        properties=props,
        timeout=DEADLINE_S,
    ) as c:
        yield c


async def first_message(c: aiomqtt.Client) -> aiomqtt.Message:
    async def first() -> aiomqtt.Message:
        async for message in c.messages:
            return message
        raise AssertionError("the client's message stream ended")

    async with asyncio.timeout(DEADLINE_S):
        return await first()


@pytest.fixture
async def broker(tmp_path: Path) -> AsyncIterator[MosquittoBroker]:
    async with MosquittoBroker(tmp_path / "broker", CELLS) as b:
        yield b


async def test_broker_starts_on_loopback_with_private_files(broker: MosquittoBroker) -> None:
    assert broker.url == f"mqtt://127.0.0.1:{broker.port}"
    for user in ("factory", "cell1", "cell2"):
        path = broker.credentials(user)
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
        assert login(broker, user)[0] == user
    for name in ("passwd", "acl", "mosquitto.conf"):
        assert stat.S_IMODE(os.stat(broker.directory / name).st_mode) == 0o600
    async with client(broker, "factory") as factory:
        await factory.subscribe("cellctl/cell1/status", qos=1)
        async with client(broker, "cell1") as cell:
            await cell.publish("cellctl/cell1/status", b"online", qos=1)
        assert (await first_message(factory)).payload == b"online"


async def test_wrong_password_and_unknown_user_refused(broker: MosquittoBroker) -> None:
    for username, password in (("cell1", "not-the-password"), ("nobody", "x"), ("cell1", "")):
        with pytest.raises(aiomqtt.MqttError):
            async with aiomqtt.Client(
                "127.0.0.1", broker.port, username=username, password=password, timeout=3
            ):
                pass


async def test_a_cell_cannot_read_another_cells_orders(broker: MosquittoBroker) -> None:
    async with client(broker, "factory") as factory, client(broker, "cell2") as cell2:
        # The broker refuses the subscription outright, or accepts it and never delivers.
        with suppress(aiomqtt.MqttError):
            await cell2.subscribe("cellctl/cell1/orders", qos=1)
        await cell2.subscribe("cellctl/cell2/orders", qos=1)
        await factory.publish("cellctl/cell1/orders", b'{"v":1,"id":"secret"}', qos=1)
        await factory.publish("cellctl/cell2/orders", b'{"v":1,"id":"mine"}', qos=1)
        message = await first_message(cell2)
        assert message.topic.value == "cellctl/cell2/orders"
        assert message.payload == b'{"v":1,"id":"mine"}'


async def test_a_cell_cannot_post_another_cells_reports(broker: MosquittoBroker) -> None:
    async with (
        client(broker, "factory") as factory,
        client(broker, "cell1") as cell1,
        client(broker, "cell2") as cell2,
    ):
        await factory.subscribe("cellctl/cell1/reports", qos=1)
        await factory.subscribe("cellctl/cell1/state", qos=1)
        for topic in ("cellctl/cell1/reports", "cellctl/cell1/state"):
            # Under MQTT 5 the PUBACK says "not authorized"; either way nothing goes out.
            with suppress(aiomqtt.MqttError):
                await cell2.publish(topic, b'{"v":1,"cell":"cell1","forged":true}', qos=1)
        await cell1.publish("cellctl/cell1/reports", b'{"v":1,"cell":"cell1","seq":1}', qos=1)
        message = await first_message(factory)
        assert message.payload == b'{"v":1,"cell":"cell1","seq":1}'
        # A cell cannot write orders either, not even its own.
        await cell1.subscribe("cellctl/cell1/orders", qos=1)
        with suppress(aiomqtt.MqttError):
            await cell1.publish("cellctl/cell1/orders", b'{"v":1,"id":"self"}', qos=1)
        await factory.publish("cellctl/cell1/orders", b'{"v":1,"id":"real"}', qos=1)
        assert (await first_message(cell1)).payload == b'{"v":1,"id":"real"}'


async def test_a_message_larger_than_any_reader_takes_never_passes_the_broker(
    broker: MosquittoBroker,
) -> None:
    """One cell's credentials cannot push a message larger than the factory reads into the
    factory's memory or the broker's store: its sender is disconnected at the door, nothing
    is delivered or kept retained; one at the limit passes."""
    from cellctl.mailbox.wire import MAX_PAYLOAD

    async with client(broker, "factory") as factory:
        await factory.subscribe("cellctl/cell1/state", qos=1)
        with suppress(aiomqtt.MqttError):  # disconnected: the publish or the exit fails
            async with client(broker, "cell1") as cell1:
                big = b"x" * (4 * MAX_PAYLOAD)
                await cell1.publish("cellctl/cell1/state", big, qos=1, retain=True)
        async with client(broker, "cell1") as cell1:
            fits = b"y" * MAX_PAYLOAD
            await cell1.publish("cellctl/cell1/state", fits, qos=1, retain=True)
        assert (await first_message(factory)).payload == fits  # the first to arrive
    # What the broker keeps retained is the one that fitted.
    async with client(broker, "factory") as late:
        await late.subscribe("cellctl/cell1/state", qos=1)
        kept = await first_message(late)
        assert kept.payload == fits and kept.retain


async def test_restart_keeps_a_queued_message_for_a_persistent_session(
    broker: MosquittoBroker,
) -> None:
    async with client(broker, "cell1", client_id="cellctl-cell-cell1", persistent=True) as cell:
        await cell.subscribe("cellctl/cell1/orders", qos=1)
    async with client(broker, "factory") as factory:
        await factory.publish("cellctl/cell1/orders", b'{"v":1,"id":"while-away"}', qos=1)
    port = broker.port
    await broker.restart()
    assert broker.port == port
    async with client(broker, "cell1", client_id="cellctl-cell-cell1", persistent=True) as cell:
        # No new subscription: the session and its queued message came back from disk.
        message = await first_message(cell)
    assert message.payload == b'{"v":1,"id":"while-away"}'


async def test_two_cells_with_one_prefix_refused(tmp_path: Path) -> None:
    from cellctl.errors import UsageError

    with pytest.raises(UsageError, match="same topic prefix"):
        MosquittoBroker(tmp_path, [("a", "x/y"), ("b", "x/y")])
    with pytest.raises(UsageError, match="wildcards"):
        MosquittoBroker(tmp_path, [("a", "x/#")])


def _block_after(text: str, marker: str) -> str:
    """The fenced block that follows ``marker`` in ``text``."""
    rest = text[text.index(marker) :]
    start = rest.index("```\n") + 4
    return rest[start : rest.index("```", start)]


def test_the_documented_production_configuration_is_the_one_the_tests_run() -> None:
    """docs/factory.md's broker configuration and ACL are what MosquittoBroker runs (its
    global and listener lines come from the same functions, with its own paths)."""
    from cellctl.factory.broker import acl, production_conf

    docs = (Path(__file__).resolve().parent.parent / "docs" / "factory.md").read_text()
    assert _block_after(docs, "`/etc/mosquitto/conf.d/cellctl.conf`:") == production_conf()
    assert _block_after(docs, "`/etc/mosquitto/acl`:") == acl([("cell1", "cellctl/cell1")])
    # Client ids are bound to users on the documented listener: the option follows it.
    lines = production_conf().splitlines()
    listener = next(i for i, line in enumerate(lines) if line.startswith("listener "))
    assert "use_username_as_clientid true" in lines[listener:]


async def test_every_listener_binds_client_ids_to_users(broker: MosquittoBroker) -> None:
    conf = (broker.directory / "mosquitto.conf").read_text().splitlines()
    listeners = [i for i, line in enumerate(conf) if line.startswith("listener ")]
    assert listeners and all(conf[i + 1] == "use_username_as_clientid true" for i in listeners)
    # cell2 with the factory's client id takes only its own session: the factory stays on.
    async with client(broker, "factory", client_id="cellctl-factory-factory") as factory:
        await factory.subscribe("cellctl/cell1/status", qos=1)
        async with client(broker, "cell2", client_id="cellctl-factory-factory"):
            pass
        async with client(broker, "cell1") as cell1:
            await cell1.publish("cellctl/cell1/status", b"online", qos=1)
        assert (await first_message(factory)).payload == b"online"
    log = broker.log_path.read_text()
    assert "New client connected from" in log and "Client factory already connected" not in log
    # Only the listeners configured: no default listener on 1883 beside them.
    opened = [line for line in log.splitlines() if "listen socket on port" in line]
    assert {line.rsplit(" ", 1)[1].rstrip(".") for line in opened} == {str(broker.port)}


async def test_two_programs_on_one_user_are_told_they_take_turns(broker: MosquittoBroker) -> None:
    """The broker keeps one connection per user (its client id): two programs with one set of
    credentials (a second `cellctl factory run` on another host) drop each other for ever.
    Each says so in its log after a few such drops, not only "connection lost"."""
    settings = MqttSettings.load(broker.url + "/factory", broker.credentials("factory"), None)
    stop, both_told = asyncio.Event(), asyncio.Event()
    logs: dict[str, list[str]] = {"first": [], "second": []}

    def logger(name: str) -> Callable[[str], None]:
        def log(line: str) -> None:
            logs[name].append(line)
            if told("first") and told("second"):
                both_told.set()

        return log

    links = {
        name: Reconnect(
            settings, stop, log=logger(name), what=name, errors=(aiomqtt.MqttError,),
            twin="a second copy of this program",
        )
        for name in logs
    }  # fmt: skip

    def told(name: str) -> bool:
        return any("is a second copy of this program (factory)?" in line for line in logs[name])

    first_in = asyncio.Event()

    async def drain(c: aiomqtt.Client) -> None:
        async for _ in c.messages:  # until the broker drops it: MqttError
            pass

    async def session(link: Reconnect) -> None:
        async with settings.client("ignored: the broker names it after its user") as c:
            link.connected()
            first_in.set()
            # Until dropped, or told to stop. Not on the cancel alone: Python 3.11's
            # asyncio.wait_for (under aiomqtt's connect) loses a cancel that comes as the
            # broker's CONNACK does, and the session would then wait here for ever.
            dropped, stopped = asyncio.create_task(drain(c)), asyncio.create_task(stop.wait())
            try:
                await asyncio.wait({dropped, stopped}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                dropped.cancel()
                stopped.cancel()
            if not stop.is_set():
                await dropped  # raises its MqttError

    # The second starts once the first is in, as a second controller would: two connections
    # made in the same instant can leave the dropped one unaware of it (aiomqtt), which is
    # not what this is about.
    tasks = [asyncio.create_task(links["first"].run(lambda: session(links["first"])))]
    async with asyncio.timeout(30):
        await first_in.wait()
    tasks.append(asyncio.create_task(links["second"].run(lambda: session(links["second"]))))
    try:
        async with asyncio.timeout(20):
            await both_told.wait()
    finally:
        stop.set()
        for task in tasks:
            task.cancel()
        # A link told to stop ends within its client's own deadlines (2 s each): said so,
        # not left to the suite's timeout.
        try:
            async with asyncio.timeout(20):
                await asyncio.gather(*tasks, return_exceptions=True)
        except TimeoutError:
            where = {t.get_name(): [repr(f) for f in t.get_stack()] for t in tasks if not t.done()}
            raise AssertionError(
                f"a link did not end within 20 s of its stop: {logs}; still in {where}"
            ) from None
    for lines in logs.values():
        assert "take turns" in lines[-1], lines
        # Said once, after drops that did not say it: a single drop is not a twin.
        assert sum("take turns" in line for line in lines) == 1, lines
        assert "take turns" not in lines[0], lines


async def first_words(settings: MqttSettings, what: str, **options: Any) -> list[str]:
    """What a :class:`Reconnect` to ``settings`` logs (``what`` its label) until its first
    line, its session never connecting; stopped then."""
    stop, told = asyncio.Event(), asyncio.Event()
    lines: list[str] = []

    def log(line: str) -> None:
        lines.append(line)
        told.set()

    async def session() -> None:
        async with settings.client("cell1"):
            raise AssertionError("connected where no broker answers")

    link = Reconnect(settings, stop, log=log, what=what, **options)
    task = asyncio.create_task(link.run(session))
    try:
        async with asyncio.timeout(30):
            await told.wait()
    finally:
        stop.set()
        async with asyncio.timeout(20):
            await task
    return lines


async def test_a_broker_that_never_answers_is_said_so_in_words() -> None:
    """Something listens at the broker's address and never answers (a stuck broker, a port
    forwarded to nothing): the link says the broker did not answer, not the library's bare
    "Operation timed out", and keeps trying."""

    async def silent(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read()  # takes the CONNECT, answers nothing, until the client hangs up
        writer.close()

    server = await asyncio.start_server(silent, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    settings = MqttSettings("127.0.0.1", port, "factory", "cell1", "its-password")
    try:
        lines = await first_words(settings, "cell1", errors=(aiomqtt.MqttError,))
    finally:
        server.close()
    assert lines[0] == (
        f"cell1: mqtt://127.0.0.1:{port}/factory: the broker at 127.0.0.1:{port} "
        "did not answer within 2 s (trying again)"
    ), lines
    assert "Operation timed out" not in "".join(lines)
