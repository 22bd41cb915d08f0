"""A watched private Mosquitto that dies (``kill -9`` from outside) is said and started again
on the same port with the same configuration and persistence; one that will not start again
is said with what to do; one stopped on purpose is left stopped. Against the real
/usr/sbin/mosquitto, and end to end through ``cellctl emulate factory``."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
from collections.abc import AsyncIterator
from pathlib import Path
from typing import IO

import pytest

from cellctl.factory.broker import MosquittoBroker

from .conftest import CELLCTL, until, wait_until
from .test_broker import CELLS, client, first_message

RESTARTS = 3


@pytest.fixture
async def watched(tmp_path: Path) -> AsyncIterator[tuple[MosquittoBroker, list[str]]]:
    said: list[str] = []
    async with MosquittoBroker(
        tmp_path / "broker", CELLS, restarts=RESTARTS, say=said.append
    ) as broker:
        yield broker, said


def broker_pid(broker: MosquittoBroker) -> int:
    process = broker._process  # the test kills it from outside, as a user's kill -9 would
    assert process is not None and process.returncode is None
    return process.pid


async def test_a_broker_killed_is_started_again_with_its_port_and_persisted_sessions(
    watched: tuple[MosquittoBroker, list[str]],
) -> None:
    broker, said = watched
    async with client(broker, "cell1", client_id="cellctl-cell-cell1", persistent=True) as cell:
        await cell.subscribe("cellctl/cell1/orders", qos=1)
    async with client(broker, "factory") as factory:
        await factory.publish("cellctl/cell1/orders", b'{"v":1,"id":"while-away"}', qos=1)
    database = broker.directory / "data" / "mosquitto.db"
    await until(
        lambda: database.exists() and b"while-away" in database.read_bytes(),
        "the broker to save the queued message",
    )
    port, first = broker.port, broker_pid(broker)

    os.kill(first, signal.SIGKILL)
    await until(lambda: any("is back" in line for line in said), "the broker to be back")

    assert said[0].startswith(f"Mosquitto on 127.0.0.1:{port} stopped (killed by signal 9)")
    assert "starting it again" in said[0]
    assert "reconnect by themselves" in said[1]
    assert broker.port == port and broker.running and broker_pid(broker) != first
    assert broker.failure is None
    # The same passwords and the persisted session: the message queued before the kill.
    async with client(broker, "cell1", client_id="cellctl-cell-cell1", persistent=True) as cell:
        assert (await first_message(cell)).payload == b'{"v":1,"id":"while-away"}'

    # And again: the watch goes on with the new process.
    os.kill(broker_pid(broker), signal.SIGKILL)
    await until(lambda: sum("is back" in line for line in said) == 2, "the broker back twice")
    assert broker.running


def kill_with_a_store_it_cannot_read(broker: MosquittoBroker) -> None:
    """Kill the broker with a persistence file Mosquitto cannot read, which makes every start
    fail ("Unrecognised file format"); frozen first, so it cannot save over it."""
    pid = broker_pid(broker)
    os.kill(pid, signal.SIGSTOP)
    (broker.directory / "data" / "mosquitto.db").write_bytes(b"not a database")
    os.kill(pid, signal.SIGKILL)


async def test_a_broker_that_will_not_start_again_is_said_with_what_to_do(
    watched: tuple[MosquittoBroker, list[str]],
) -> None:
    broker, said = watched
    kill_with_a_store_it_cannot_read(broker)
    await until(
        lambda: broker.failure is not None and "attempts" in said[-1], "the watch to give up"
    )

    assert not broker.running
    attempts = [line for line in said if line.startswith("Mosquitto did not start")]
    assert [line.split("(")[1].split(")")[0] for line in attempts] == [
        f"attempt {n} of {RESTARTS}" for n in range(1, RESTARTS + 1)
    ]
    assert "Error: Couldn't open database" in attempts[0]  # the broker's own reason (its stderr)
    final = said[-1]
    assert f"did not start again in {RESTARTS} attempts" in final
    assert str(broker.directory) in final and "Ctrl-C" in final
    assert str(broker.failure) == final


async def test_a_broker_stopped_or_killed_on_purpose_is_not_started_again(
    watched: tuple[MosquittoBroker, list[str]],
) -> None:
    broker, said = watched
    await broker.stop()
    assert not broker.running
    await broker.start()  # watched again once started
    await broker.kill()
    assert not broker.running
    assert said == []


def _lines_into(stream: IO[str], lines: list[str]) -> threading.Thread:
    thread = threading.Thread(target=lambda: lines.extend(stream), daemon=True)
    thread.start()
    return thread


def test_emulate_factory_says_its_broker_died_and_starts_it_again(tmp_path: Path) -> None:
    plant = tmp_path / "plant"
    proc = subprocess.Popen(
        [*CELLCTL, "emulate", "factory", "--cells", "2", str(plant)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    out: list[str] = []
    err: list[str] = []
    assert proc.stdout is not None and proc.stderr is not None
    readers = [_lines_into(proc.stdout, out), _lines_into(proc.stderr, err)]
    try:
        wait_until(lambda: "serving until Ctrl-C\n" in out or proc.poll() is not None, "serving")
        assert proc.poll() is None, "".join(out + err)
        conf = str(plant / "broker" / "mosquitto.conf")
        pid = _process_with(conf)
        os.kill(pid, signal.SIGKILL)
        wait_until(lambda: any("is back on" in line for line in err), "the broker back")
        assert "stopped (killed by signal 9): starting it again" in err[0]
        assert proc.poll() is None  # still serving, with its broker
        assert _process_with(conf) != pid
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
        for reader in readers:
            reader.join(10)
    assert "emulated factory stopped\n" in out
    assert proc.returncode == 0


def _process_with(argument: str) -> int:
    """The pid of the one process whose command line has ``argument``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            args = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if argument.encode() in args:
            found.append(int(entry.name))
    assert len(found) == 1, found
    return found[0]


async def test_a_stop_while_the_broker_is_started_again_ends_the_watch(
    watched: tuple[MosquittoBroker, list[str]],
) -> None:
    broker, said = watched
    kill_with_a_store_it_cannot_read(broker)
    await until(lambda: any("attempt 1 of" in line for line in said), "a first failed attempt")
    await broker.stop()  # returns once the watch has ended: nothing is tried after it
    tried = list(said)
    assert not broker.running
    assert not any("did not start again" in line for line in tried)
    await broker.stop()
    assert said == tried
