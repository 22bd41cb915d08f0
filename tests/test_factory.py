"""The factory end to end: a real Mosquitto on loopback, three emulated cells with their
``cellctl run`` controllers and ``cellctl factory run``, each its own process, and 30 orders
of both part types. Three faults, each in its own test: a cell controller killed with -9
mid-cut and started again, the broker stopped mid-batch and started again, the factory
controller killed with -9 and started again. After each, every order's parts were made once:

- from the mills' own logs (``EmulatedCell.runs_per_part``): every physical part cut once on
  each mill of its route, and as many parts cut as were ordered;
- from the reports: each order done in the factory's store, and in exactly one cell's
  SQLite mailbox (not cancelled), done there with its quantity of parts.

The emulated machines and the broker live in the test process (so the mills' logs can be
read); the controllers are subprocesses whose output goes to log files shown on failure.
Then the broker's ACLs with the credentials ``EmulatedFactory`` hands out; malformed
states, reports and orders, which stop neither the factory nor a cell (over the broker, and
as hypothesis properties); and the factory's command line (an unknown part type, a priority
too large, a second ``run``, a broken factory.toml).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import os
import signal
import stat
import subprocess
import tempfile
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from rich.console import Console

from cellctl.cell.config import load_cell
from cellctl.cell.journal import Journal, open_journal
from cellctl.emulators.cell import EmulatedCell
from cellctl.errors import UsageError
from cellctl.factory.config import FactoryConfig, load_factory
from cellctl.factory.controller import FactoryController
from cellctl.factory.dispatch import choose
from cellctl.factory.emulated import EmulatedFactory
from cellctl.factory.store import DONE, FINAL_STATES, OPEN_STATES, FactoryStore
from cellctl.mailbox import CANCELLED, Mailbox, open_mailbox
from cellctl.mailbox.mqtt import parse_order, read_credentials
from cellctl.ui.factory_cli import cells_table
from tests.cell_rig import TIME_SCALE, cli, write_cell_options

from .conftest import CELLCTL

PART_TYPES = ("wax-robot-base", "wax-toy-mill-table")
#: The batch: 30 orders of both types, every fifth for two parts; the last ten are submitted
#: while the fault is on (an order comes in while a cell, the broker or the factory is away).
BATCH = [(f"F{n:02d}", PART_TYPES[n % 2], 2 if n % 5 == 0 else 1) for n in range(1, 31)]
FIRST, DURING = BATCH[:20], BATCH[20:]
#: Deadline of one wait for the plant (the whole batch takes about 12 s on an idle box).
WAIT_S = 60.0
#: Deadline of one operator command.
CLI_S = 30.0
#: A pallet asked for comes within milliseconds here: ask again after 2 s, not the example
#: cell's 60. (A controller killed between the two writes of its pallet_request pulse leaves
#: the coil high, so its successor's first pulse makes no rising edge and the conveyor never
#: hears it: only this timeout's alarm and second request get the cell going again.)
CELL_OPTIONS = {"pallet_timeout": 2.0}
MILL_INDEX = {"cnc1": 1, "cnc2": 2}


class Plant:
    """An :class:`EmulatedFactory` in this process; its cells' controllers and the factory
    controller as ``cellctl`` subprocesses, started and killed by name (``cell2``, ``factory``).
    """

    def __init__(self, directory: Path, *, cells: int = 3) -> None:
        self.directory = directory
        self.emulated = EmulatedFactory(
            directory, cells=cells, time_scale=TIME_SCALE, poll_period=0.1, factory_poll=0.1
        )
        self.logs = directory / "logs"
        self.procs: dict[str, asyncio.subprocess.Process] = {}
        self.store: FactoryStore
        self.journals: dict[str, Journal] = {}
        self.mailboxes: dict[str, Mailbox] = {}

    @property
    def names(self) -> list[str]:
        return self.emulated.names

    def cell(self, name: str) -> EmulatedCell:
        return self.emulated.cells[self.names.index(name)]

    def cell_dir(self, name: str) -> Path:
        return self.directory / name

    async def __aenter__(self) -> Plant:
        await self.emulated.start()
        try:
            for name in self.names:
                write_cell_options(self.cell_dir(name) / "cell.toml", CELL_OPTIONS, {})
            self.logs.mkdir()
            self.store = FactoryStore(load_factory(self.directory).state_path)
            for name in self.names:
                self.journals[name] = open_journal(self.cell_dir(name))
                self.mailboxes[name] = open_mailbox(self.cell_dir(name))
        except BaseException:
            await self.emulated.close()
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        try:
            for name in list(self.procs):
                await self.stop(name)
        finally:
            for journal in self.journals.values():
                journal.close()
            for mailbox in self.mailboxes.values():
                mailbox.close()
            self.store.close()
            await self.emulated.close()

    # -- the controllers ---------------------------------------------------------------------

    async def start(self, name: str) -> asyncio.subprocess.Process:
        """Start ``cellctl run`` of cell ``name``, or ``cellctl factory run`` for "factory"."""
        assert name not in self.procs, f"{name} is running"
        if name == "factory":
            args = ["factory", "--dir", str(self.directory), "run", "--no-live"]
        else:
            args = ["--cell", str(self.cell_dir(name)), "run", "--no-live"]
        with (self.logs / f"{name}.log").open("ab") as log:
            log.write(f"---- started {' '.join(args)}\n".encode())
            log.flush()
            proc = await asyncio.create_subprocess_exec(
                *CELLCTL,
                *args,
                stdin=asyncio.subprocess.DEVNULL,
                stdout=log,
                stderr=asyncio.subprocess.STDOUT,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        self.procs[name] = proc
        return proc

    async def kill(self, name: str) -> None:
        """kill -9 ``name``'s process."""
        proc = self.procs.pop(name)
        assert proc.returncode is None, f"{name} had already exited\n{self.describe()}"
        proc.send_signal(signal.SIGKILL)
        await proc.wait()

    async def stop(self, name: str) -> None:
        """SIGTERM ``name``'s process (killed if it does not exit within 15 s)."""
        proc = self.procs.pop(name)
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
        try:
            await asyncio.wait_for(proc.wait(), 15)
        except TimeoutError:
            proc.kill()
            await proc.wait()

    async def start_all(self) -> None:
        """Every cell's controller and the factory's; returns once the factory knows what
        each cell makes."""
        for name in [*self.names, "factory"]:
            await self.start(name)
        await self.wait_for(
            lambda: (
                all(
                    set(PART_TYPES) <= set(c.part_types) and c.status == "online"
                    for c in self.store.cells().values()
                )
                and set(self.store.cells()) == set(self.names)
            ),
            "the factory hears every cell online with its part types",
        )

    # -- orders --------------------------------------------------------------------------------

    def submit(self, batch: list[tuple[str, str, int]]) -> None:
        """What ``cellctl factory submit`` does, for each order of ``batch``."""
        for oid, part_type, qty in batch:
            _, new = self.store.submit(part_type, qty, priority=0, order_id=oid)
            assert new

    def done(self) -> set[str]:
        return {o.id for o in self.store.orders([DONE])}

    def cells_done(self) -> set[str]:
        """Orders some cell's own mailbox says are done."""
        return {o.id for mb in self.mailboxes.values() for o in mb.orders() if o.state == DONE}

    def cutting(self) -> str | None:
        """A cell whose journal has a cut in flight that its emulated mill is running on a
        part (and more work to do after it), or None."""
        for name, journal in self.journals.items():
            for step in journal.open_steps():
                mill = self.cell(name).mills.get(step.machine)
                if step.kind != "machine" or mill is None or not mill.executing:
                    continue
                if self.cell(name).vise[MILL_INDEX[step.machine]] is None:
                    continue
                if len(self.journals[name].parts(statuses=["waiting"])) > 0:
                    return name
        return None

    def held(self) -> dict[str, list[str]]:
        return {
            name: [p.id for p in j.parts(statuses=["held"])]
            for name, j in self.journals.items()
            if j.parts(statuses=["held"])
        }

    def reports_caught_up(self) -> bool:
        """The factory has every report each cell made (their seqs are 1, 2, 3 ...)."""
        seen = self.store.cells()
        for name, mailbox in self.mailboxes.items():
            reports = mailbox.reports()
            if reports and (name not in seen or seen[name].seq < reports[-1].seq):
                return False
        return True

    # -- waiting -------------------------------------------------------------------------------

    async def wait_for(
        self, condition: Callable[[], Any], what: str, timeout: float = WAIT_S
    ) -> Any:
        """Poll ``condition`` until it is true; fail at once if a controller died, or with
        the plant's state after ``timeout``."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            value = condition()
            if value:
                return value
            for name, proc in self.procs.items():
                if proc.returncode is not None:
                    raise AssertionError(
                        f"{name} exited ({proc.returncode}) while waiting for: {what}\n"
                        + self.describe()
                    )
            if loop.time() > deadline:
                raise AssertionError(
                    f"timed out after {timeout:g} s waiting for: {what}\n{self.describe()}"
                )
            await asyncio.sleep(0.05)

    async def finish(self, *, operator: bool = False) -> None:
        """Until every order is done and the factory has every report. With ``operator``
        the operator inspects each held part as it comes; without, a held part fails."""
        for _ in range(10):
            await self.wait_for(
                lambda: (
                    (len(self.done()) == len(BATCH) and self.reports_caught_up()) or self.held()
                ),
                "every order done, the factory up to date with every cell's reports",
            )
            held = self.held()
            if not held:
                return
            assert operator, f"parts held: {held}\n{self.describe()}"
            for name in held:
                await self.operator_inspects(name)
        raise AssertionError(f"still parts held after 10 inspections\n{self.describe()}")

    async def operator_inspects(self, name: str) -> None:
        """The operator clears cell ``name``'s alarms, looks at each held part in the cell
        (the emulators' physical state) and releases it as it is: a part in a vise whose
        mill's log shows its cut counts as cut; a transfer's part is where the robot left it."""
        cell, journal, cell_dir = self.cell(name), self.journals[name], self.cell_dir(name)

        async def operator(*args: str) -> None:
            try:
                result = await asyncio.wait_for(cli(cell_dir, *args), CLI_S)
            except TimeoutError:
                raise AssertionError(
                    f"cellctl {' '.join(args)}: no answer\n{self.describe()}"
                ) from None
            assert result.exit_code == 0, f"{args}: {result.output}\n{self.describe()}"

        for alarm in journal.active_alarms():
            await operator("alarm", "clear", str(alarm.id))
        for part in journal.parts(statuses=["held"]):
            step = journal.steps(part.id)[-1]
            if step.kind == "transfer":
                source, target = step.program.split("_to_")
                assert cell.gripper is None, f"{part.id} in the gripper\n{self.describe()}"
                if target == "conveyor":
                    made = sum(p.status == "done" for p in journal.parts())
                    where = "out" if len(cell.outfeed) > made else source
                else:
                    where = target if cell.vise[MILL_INDEX[target]] is not None else source
                await operator("part", "release", part.id, "--at", where)
            else:
                blank = cell.vise[MILL_INDEX[step.machine]]
                assert blank is not None, (
                    f"{part.id}: {step.machine}'s vise empty\n{self.describe()}"
                )
                cut = cell.runs_per_part().get(blank, {}).get(step.machine, 0)
                await operator("part", "release", part.id, *([] if cut else ["--redo"]))

    def _physical(self, name: str) -> list[str]:
        """What the emulators of cell ``name`` say: where the parts are, the PLC's signals."""
        cell = self.cell(name)
        plc = cell.plc
        on = [n for n, v in {**plc.inputs, **plc.coils}.items() if v]
        return [
            f"  mills cut: {cell.runs_per_part()}",
            f"  pallet {cell.pallet_part} gripper {cell.gripper} vises {cell.vise}"
            f" outfeed {cell.outfeed}",
            f"  plc on: {on} pallets delivered {plc.pallets_delivered}"
            f" timers {sorted(plc._timers)}",
            "  mills: "
            + ", ".join(
                f"{m}: {mill.display} executing={mill.executing}" for m, mill in cell.mills.items()
            ),
            f"  robot state {cell.robot.state}",
        ]

    def describe(self) -> str:
        """The factory's orders and events, each cell's open work, the processes' logs."""
        lines = ["factory orders:"]
        lines += [
            f"  {o.id} {o.part_type} x{o.qty} {o.state} cell={o.cell} done={o.done}"
            f" held={o.held} sends={o.sends} refused={list(o.refused)} {o.note}"
            for o in self.store.orders()
        ]
        lines.append("factory cells:")
        lines += [
            f"  {c.name} {c.status} seq={c.seq} orders_open={c.state.get('orders_open')}"
            for c in self.store.cells().values()
        ]
        lines.append("factory events (last 30):")
        lines += [f"  {e.cell or '-'} {e.text}" for e in self.store.events(limit=30)]
        for name in self.names:
            journal, mailbox = self.journals[name], self.mailboxes[name]
            lines.append(f"{name}: last report {mailbox.reports()[-1:]}")
            lines += [f"  order {o.id} {o.state} {o.note}" for o in mailbox.orders()]
            lines += [
                f"  part {p.id} {p.order_id} {p.location} r{p.route_index} {p.status} {p.note}"
                for p in journal.parts()
                if p.status != "done"
            ]
            lines += [
                f"  open step {s.id} {s.part_id} {s.kind} {s.machine} {s.program}"
                for s in journal.open_steps()
            ]
            lines += [
                f"  alarm {a.id} {a.machine} {a.code} {a.text}" for a in journal.active_alarms()
            ]
            lines += self._physical(name)
        for log in sorted(self.logs.glob("*.log")):
            tail = log.read_text(errors="replace").splitlines()[-40:]
            lines += [f"---- {log.name} (last 40 lines)", *tail]
        broker_log = self.emulated.broker.log_path
        if broker_log.exists():
            lines += ["---- broker (last 15 lines)"]
            lines += broker_log.read_text(errors="replace").splitlines()[-15:]
        return "\n".join(lines)

    # -- the checks ----------------------------------------------------------------------------

    def check_made_once(self) -> None:
        """Every order done, by one cell, with its parts cut once on each mill of its route."""
        state = self.describe()
        orders = {o.id: o for o in self.store.orders()}
        assert set(orders) == {oid for oid, _, _ in BATCH}, state
        for oid, part_type, qty in BATCH:
            o = orders[oid]
            assert (o.part_type, o.qty, o.state, o.done) == (part_type, qty, DONE, qty), state
            # The cells' own records: taken by exactly one cell, the one the factory says.
            holders = [
                name
                for name, mailbox in self.mailboxes.items()
                if any(c.id == oid and c.state != CANCELLED for c in mailbox.orders())
            ]
            assert holders == [o.cell], f"order {oid} at {holders}, factory says {o.cell}\n{state}"
            at = self.mailboxes[o.cell].get_order(oid)
            assert (at.state, at.qty, at.part_type) == (DONE, qty, part_type), state
            parts = self.journals[o.cell].parts(order_id=oid)
            assert [p.status for p in parts] == ["done"] * qty, state
        # No cell has an order the factory did not give it.
        for mailbox in self.mailboxes.values():
            assert {c.id for c in mailbox.orders()} <= set(orders), state
        # The accept deadline's alarm bell: an order accepted by a second cell.
        assert not [e.text for e in self.store.events(limit=10_000) if " too, after " in e.text]
        # The mills' own logs: each part cut once on each mill of its route, as many parts
        # as ordered from each cell, and every one of them out on the conveyor.
        for name in self.names:
            cell = self.cell(name)
            routes = load_cell(self.cell_dir(name)).parts
            mills = {t: sorted(step.mill for step in routes[t].route) for t in PART_TYPES}
            assert mills[PART_TYPES[0]] == mills[PART_TYPES[1]], "the check below needs one route"
            runs = cell.runs_per_part()
            ordered = sum(o.qty for o in orders.values() if o.cell == name)
            assert len(runs) == ordered, (
                f"{name}: {len(runs)} parts cut, {ordered} ordered\n{state}"
            )
            once = dict.fromkeys(mills[PART_TYPES[0]], 1)
            assert {p: r for p, r in runs.items() if r != once} == {}, f"{name}\n{state}"
            assert sorted(cell.outfeed) == sorted(runs), f"{name}\n{state}"
        total = sum(len(self.cell(n).runs_per_part()) for n in self.names)
        assert total == sum(qty for _, _, qty in BATCH), state
        # The factory spread the batch over every cell.
        assert {o.cell for o in orders.values()} == set(self.names), state


@pytest.fixture
async def plant(tmp_path: Path) -> AsyncIterator[Plant]:
    """Broker, three emulated cells, their controllers and the factory's, all running."""
    async with Plant(tmp_path / "plant") as p:
        await p.start_all()
        yield p


# -- the batch through a fault ---------------------------------------------------------------


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
        async with logged_in(port, plant.cell_dir("cell1") / "mqtt.toml") as cell1:
            for topic, payloads in MALFORMED.items():
                for payload in payloads:
                    await cell1.publish(f"cellctl/cell1/{topic}", json.dumps(payload), qos=1)
        async with logged_in(port, plant.directory / "factory.credentials") as factory:
            for order in POISONED_ORDERS:
                await factory.publish("cellctl/cell1/orders", json.dumps(order), qos=1)
        count = sum(len(p) for p in MALFORMED.values())

        def ignored() -> list[str]:
            events = plant.store.events(limit=10_000)[before:]
            return [e.text for e in events if e.cell == "cell1" and "ignored" in e.text]

        await plant.wait_for(lambda: len(ignored()) >= count, "the factory ignores each of them")
        assert len(ignored()) == count, ignored()
        log = plant.logs / "cell1.log"
        await plant.wait_for(
            lambda: log.read_text().count("order refused") == len(POISONED_ORDERS),
            "the cell refuses each poisoned order",
        )
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
        "seq": st.integers(min_value=-2, max_value=2**64) | _JSON,
        "kind": st.sampled_from(["order-accepted", "order-rejected", "order-done"]) | _JSON,
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
            fields = parse_order(json.dumps(order).encode())
            mailbox.post_order(fields["part_type"], fields["qty"], fields["priority"], fields["id"])
        except UsageError:
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
        out, _ = await asyncio.wait_for(proc.communicate(), 60)
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
