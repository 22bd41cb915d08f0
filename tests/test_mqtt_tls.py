"""The broker over TLS, as docs/factory.md sends production users: the tests' Mosquitto gets a
TLS listener whose certificate a CA made by the test signed. A cell and the factory reach it
with ``mqtts://`` and ``ca``, and an order goes through; a CA that did not sign the broker's
certificate, ``mqtt://`` to the TLS port and ``mqtts://`` to the plain one are each refused
with a message that says which. Client ids are bound to users on the TLS listener too."""

from __future__ import annotations

import asyncio
import contextlib
import shutil
from collections.abc import AsyncIterator
from pathlib import Path

import aiomqtt
import pytest

from cellctl.errors import UsageError
from cellctl.factory.broker import FACTORY_USER, MosquittoBroker, TlsFiles
from cellctl.factory.config import load_factory
from cellctl.factory.controller import FactoryController
from cellctl.factory.store import DONE, FactoryStore
from cellctl.mailbox import open_mailbox
from cellctl.mailbox.mqtt import MqttBridge
from cellctl.mailbox.mqttlink import MqttSettings, TlsRefused, WrongScheme, read_credentials
from cellctl.testing.rig import CellRig

from .conftest import CaFiles, make_ca, until

CELLS = [("cell1", "cellctl/cell1"), ("cell2", "cellctl/cell2")]


@pytest.fixture
def ca(tmp_path: Path) -> CaFiles:
    return make_ca(tmp_path / "ca")


@pytest.fixture
async def broker(tmp_path: Path, ca: CaFiles) -> AsyncIterator[MosquittoBroker]:
    tls = TlsFiles(ca.certfile, ca.keyfile)
    async with MosquittoBroker(tmp_path / "broker", CELLS, tls=tls) as b:
        yield b


def factory_dir(tmp_path: Path, broker: MosquittoBroker, url: str, ca: Path | None) -> Path:
    """A factory.toml as docs/factory.md shows it, with ``ca`` for mqtts://."""
    directory = tmp_path / "factory"
    directory.mkdir()
    shutil.copyfile(broker.credentials(FACTORY_USER), directory / "factory.credentials")
    (directory / "factory.credentials").chmod(0o600)
    lines = ["[factory]", "poll_period = 0.1", "", "[broker]", f'url = "{url}"']
    lines.append('credentials = "factory.credentials"')
    if ca is not None:
        shutil.copyfile(ca, directory / "ca.crt")
        lines.append('ca = "ca.crt"')
    for name, prefix in CELLS[:1]:
        lines += ["", f"[cells.{name}]", f'prefix = "{prefix}"']
    (directory / "factory.toml").write_text("\n".join(lines) + "\n")
    return directory


async def test_a_cell_and_the_factory_make_an_order_over_mqtts_with_a_ca(
    tmp_path: Path, broker: MosquittoBroker, ca: CaFiles
) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        controller = await rig.start_controller()
        url = f"{broker.tls_url}/cellctl/cell1"
        settings = MqttSettings.load(url, broker.credentials("cell1"), ca.ca)
        with open_mailbox(rig.directory) as mailbox:
            bridge = MqttBridge(settings, controller, mailbox, rig.journal)
            cell_task = asyncio.create_task(bridge.run())
            config = load_factory(factory_dir(tmp_path, broker, broker.tls_url, ca.ca))
            assert config.ca is not None and config.broker_url.startswith("mqtts://")
            with FactoryStore(config.state_path) as store:
                said: list[str] = []
                factory = FactoryController(config, store, log=said.append)
                stop = asyncio.Event()
                factory_task = asyncio.create_task(factory.run(stop))
                await until(lambda: "cell1" in store.cells(), "the factory hears cell1")
                store.submit("wax-robot-base", 1, order_id="T1")
                factory.poke()
                await until(lambda: store.get("T1").state == DONE, "T1 done over TLS")
                assert mailbox.get_order("T1").state == "done"
                assert [s for s in said if "trying again" in s] == []
                stop.set()
                async with asyncio.timeout(10):
                    await factory_task
            await bridge.stop()
            async with asyncio.timeout(10):
                await cell_task
        await rig.stop_controller()


async def test_a_wrong_ca_and_the_wrong_scheme_are_refused_saying_which(
    tmp_path: Path, broker: MosquittoBroker
) -> None:
    other = make_ca(tmp_path / "other", "another CA")
    # The factory trusts a CA that did not sign the broker's certificate.
    config = load_factory(factory_dir(tmp_path, broker, broker.tls_url, other.ca))
    with FactoryStore(config.state_path) as store:
        said: list[str] = []
        factory = FactoryController(config, store, log=said.append)
        stop = asyncio.Event()
        task = asyncio.create_task(factory.run(stop))
        await until(lambda: any("trying again" in s for s in said), "the factory says why")
        where = f"127.0.0.1:{broker.tls_port}"
        expected = f"TLS: the broker's certificate at {where} is not signed by the CA in"
        assert expected in said[-1] and str(config.ca) in said[-1], said
        assert isinstance(factory._reconnect.problem, TlsRefused)
        assert factory.connected_since is None
        stop.set()
        async with asyncio.timeout(10):
            await task
    # A cell's mailbox with mqtt:// to the TLS port, and mqtts:// to the plain one.
    async with CellRig(tmp_path / "cell") as rig:
        controller = await rig.start_controller()
        cases = [
            (f"mqtt://{where}/cellctl/cell1", None, f"the broker at {where} speaks TLS: use mqtts"),
            (
                f"mqtts://127.0.0.1:{broker.port}/cellctl/cell1",
                tmp_path / "ca" / "ca.crt",
                f"the broker at 127.0.0.1:{broker.port} does not speak TLS: use mqtt://",
            ),
        ]
        for url, ca_file, words in cases:
            settings = MqttSettings.load(url, broker.credentials("cell1"), ca_file)
            with open_mailbox(rig.directory) as mailbox:
                logged: list[str] = []
                bridge = MqttBridge(settings, controller, mailbox, rig.journal, log=logged.append)
                task = asyncio.create_task(bridge.run())
                await until(lambda: logged, "the cell says why")  # noqa: B023
                assert words in logged[0], logged
                assert isinstance(bridge._reconnect.problem, WrongScheme)
                assert not bridge.connected.is_set()
                await bridge.stop()
                async with asyncio.timeout(10):
                    await task
        await rig.stop_controller()
    with pytest.raises(UsageError, match="use mqtts://"):
        MqttSettings.load(f"mqtt://{where}/x", broker.credentials("cell1"), other.ca)


async def test_client_ids_are_bound_to_users_on_the_tls_listener_too(
    broker: MosquittoBroker, ca: CaFiles
) -> None:
    import ssl

    def client(user: str, identifier: str) -> aiomqtt.Client:
        username, password = read_credentials(broker.credentials(user))
        context = ssl.create_default_context(cafile=str(ca.ca))
        return aiomqtt.Client(
            "127.0.0.1",
            broker.tls_port,
            username=username,
            password=password,
            identifier=identifier,
            tls_context=context,
            timeout=5,
        )

    async with client(FACTORY_USER, "cellctl-factory-factory") as factory:
        await factory.subscribe("cellctl/cell1/status", qos=1)
        for _ in range(3):  # cell2 poses as the factory: it only ever takes its own session
            with contextlib.suppress(aiomqtt.MqttError):
                async with client("cell2", "cellctl-factory-factory"):
                    pass
        async with client("cell1", "cellctl-cell-cellctl-cell1") as cell1:
            await cell1.publish("cellctl/cell1/status", b"online", qos=1)
        async with asyncio.timeout(10):
            message = await anext(aiter(factory.messages))
        assert message.payload == b"online"
    assert "Client factory already connected" not in broker.log_path.read_text()
