"""`cellctl run`'s log keeps to cellctl's own words when its MQTT link breaks: the MQTT
library's own error lines (paho through aiomqtt: "failed to receive on socket: ...") are not
printed into it, and cellctl says the drop and the reconnect itself.

The break is a real one: the cell's broker (a real Mosquitto) is frozen, the cell sends it a
report it cannot read, and the broker is killed: the kernel answers the unread bytes with a
reset, which the library logs as an error when it reads.
"""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import pytest

from cellctl.factory.broker import MosquittoBroker
from cellctl.mailbox.mqttlink import MqttSettings

from .conftest import CELLCTL, emulated_cell_process, until
from .test_broker import first_words

CELLS = [("cell1", "cellctl/cell1")]
#: The lines the MQTT library writes on its own (paho's error log), none of cellctl's.
LIBRARY_LINES = ("failed to receive on socket", "failed to send", "timeout on socket", "Caught")


@pytest.fixture
async def broker(tmp_path: Path) -> AsyncIterator[MosquittoBroker]:
    async with MosquittoBroker(tmp_path / "broker", CELLS) as b:
        yield b


def unread_bytes_at(port: int) -> int:
    """Bytes waiting unread in the receive queues of the established connections to
    127.0.0.1:``port`` (the listening side's: /proc/net/tcp)."""
    total = 0
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        local, state, queues = fields[1], fields[3], fields[4]
        if local == f"0100007F:{port:04X}" and state == "01":  # 01: established
            total += int(queues.split(":")[1], 16)
    return total


@asynccontextmanager
async def cell_on_broker(
    tmp_path: Path, broker: MosquittoBroker
) -> AsyncIterator[tuple[Path, Path]]:
    """An emulated cell whose mailbox is ``broker``, its `cellctl run` in a process of its
    own logging to a file: the cell's directory and the log's path. Stopped with Ctrl-C."""
    with emulated_cell_process(tmp_path / "cell", "1000") as cell:
        (cell / "mqtt.toml").write_bytes(broker.credentials("cell1").read_bytes())
        os.chmod(cell / "mqtt.toml", 0o600)
        with (cell / "cell.toml").open("a") as toml:
            toml.write(
                f'\n[mailbox]\nurl = "{broker.url}/cellctl/cell1"\ncredentials = "mqtt.toml"\n'
            )
        log_path = tmp_path / "run.log"
        with log_path.open("wb") as log:
            run = subprocess.Popen(  # noqa: ASYNC220
                [sys.executable, "-m", "cellctl", "--cell", str(cell), "run", "--no-live"],
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        try:
            yield cell, log_path
        finally:
            run.send_signal(signal.SIGINT)
            try:
                run.wait(30)
            except subprocess.TimeoutExpired:
                run.kill()


@pytest.mark.timeout(180)
async def test_a_broken_link_is_told_in_cellctls_words_only(
    tmp_path: Path, broker: MosquittoBroker
) -> None:
    async with cell_on_broker(tmp_path, broker) as (cell, log_path):
        connected = f"mailbox: {broker.url}/cellctl/cell1"
        await until(lambda: connected in log_path.read_text(), "the cell on the broker")
        process = broker._process  # frozen and killed from outside, as a hang would
        assert process is not None
        os.kill(process.pid, signal.SIGSTOP)
        # An order from the cell's own operator: its reports go to the frozen broker.
        subprocess.run(  # noqa: ASYNC221
            [*CELLCTL, "--cell", str(cell), "submit", "wax-robot-base"],
            check=True,
            capture_output=True,
            timeout=60,
        )
        await until(lambda: unread_bytes_at(broker.port) > 0, "a report the broker holds")
        await broker.kill()  # the unread report: the kernel resets the cell's connection
        await broker.start()  # same port
        await until(
            lambda: log_path.read_text().count(connected) >= 2, "the cell back on the broker"
        )
    text = log_path.read_text()
    # cellctl said the drop in its own words ...
    assert f"mailbox: {broker.url}/cellctl/cell1: " in text and "(trying again)" in text, text
    # ... and the library said nothing of its own.
    assert not [line for line in text.splitlines() if line.startswith(LIBRARY_LINES)], text


@pytest.mark.timeout(180)
async def test_a_broker_that_stops_answering_for_a_while_is_told_in_words_only(
    tmp_path: Path, broker: MosquittoBroker
) -> None:
    """The broker frozen (SIGSTOP) while the cell has reports to send, then let go on: the
    cell's log says it lost the broker and is back, in cellctl's words; none of asyncio's
    "Future exception was never retrieved" tracebacks of the library's futures, none of the
    library's bare "[code:N] ..." words."""
    async with cell_on_broker(tmp_path, broker) as (cell, log_path):
        connected = f"mailbox: {broker.url}/cellctl/cell1"
        await until(lambda: connected in log_path.read_text(), "the cell on the broker")
        process = broker._process
        assert process is not None
        os.kill(process.pid, signal.SIGSTOP)
        try:
            subprocess.run(  # noqa: ASYNC221
                [*CELLCTL, "--cell", str(cell), "submit", "wax-robot-base"],
                check=True,
                capture_output=True,
                timeout=60,
            )
            # The cell gives up on the frozen broker, and tries again and again.
            await until(
                lambda: "(trying again)" in log_path.read_text(),
                "the cell trying the frozen broker again",
            )
            # A while frozen: the cell tries it again a few times (0.2 s, 0.4 s ... apart,
            # each attempt given 2 s), each attempt a connection the broker answers later.
            await asyncio.sleep(12)
        finally:
            os.kill(process.pid, signal.SIGCONT)

        def back() -> bool:
            lines = log_path.read_text().splitlines()
            return sum(line.endswith(f" {connected}") for line in lines) >= 2

        await until(back, "the cell back on the broker")
        # Its reports of the order made while the broker was frozen go out.
        await until(lambda: unread_bytes_at(broker.port) == 0, "the broker reads them")
    text = log_path.read_text()
    assert f"the broker at 127.0.0.1:{broker.port} did not answer within" in text, text
    for raw in ("never retrieved", "Traceback", "[code:", "aiomqtt.exceptions"):
        assert raw not in text, text


async def test_no_broker_at_the_address_is_said_in_words() -> None:
    """Nothing listens at the broker's address (the broker not started, a wrong port): the
    link says so in cellctl's words, not the system's bare "[Errno 111] Connection refused",
    and keeps trying."""
    with socket.socket() as s:  # a port nothing listens at: bound, never listened on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        settings = MqttSettings("127.0.0.1", port, "cellctl/cell1", "cell1", "its-password")
        lines = await first_words(settings, "mailbox")
    assert lines[0] == (
        f"mailbox: mqtt://127.0.0.1:{port}/cellctl/cell1: nothing listens at 127.0.0.1:{port}: "
        "is the broker running there? (trying again)"
    ), lines
    assert "Errno" not in "".join(lines)


def test_the_librarys_words_for_a_lost_connection_are_cellctls() -> None:
    """What the library raises when a connection it had goes away (a publish on it, its
    socket closed, an unexpected disconnection) is said as a lost connection."""
    import aiomqtt
    from paho.mqtt.packettypes import PacketTypes
    from paho.mqtt.reasoncodes import ReasonCode

    settings = MqttSettings("127.0.0.1", 1883, "cellctl/cell1", "cell1", "x")
    lost = "the connection to the broker at 127.0.0.1:1883 was lost"
    unspecified = ReasonCode(PacketTypes.DISCONNECT, identifier=128)
    for error in (
        aiomqtt.MqttCodeError(4),  # "The client is not currently connected."
        aiomqtt.MqttCodeError(7),  # "The connection was lost."
        aiomqtt.MqttCodeError(unspecified, "Unexpected disconnection"),
    ):
        assert str(settings.unanswered(error)) == lost, error
    assert settings.unanswered(aiomqtt.MqttError("something else")) is None
