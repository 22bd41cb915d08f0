"""The control API against the emulated cell, through real WebSocket and HTTP clients: every
method, bad parameters and frames, tokens, and a client that leaves in the middle of a call."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import stat
import subprocess
import threading
import urllib.error
import urllib.request
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.client import connect, unix_connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from cellctl.errors import AccessDenied, DeviceError, MachineInUse, UsageError
from cellctl.kinds import Condition
from cellctl.kinds.ibm7545.aml import compile_source
from cellctl.link.trace import SENT
from cellctl.service.access import AttachedCell, LocalCell
from cellctl.service.client import RemoteCell, attach
from cellctl.service.server import ApiServer
from cellctl.service.status import CellStatus, StepKind, apply_update_json
from cellctl.testing.rig import CellRig
from cellctl.ui.console.session import cell_refs
from tests.conftest import CELLCTL, free_port

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@dataclass
class Api:
    rig: CellRig
    server: ApiServer
    client: RemoteCell
    port: int

    @property
    def directory(self) -> Path:
        return self.rig.directory

    async def call(self, method: str, params: dict[str, Any] | None = None) -> Any:
        return await self.client.call(method, params or {})


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        assert rig.controller is not None
        port = free_port()
        server = ApiServer(AttachedCell(rig.controller), rig.directory, listen=f"127.0.0.1:{port}")
        await server.start()
        client = await attach(rig.directory)
        try:
            yield Api(rig, server, client, port)
        finally:
            await client.close()
            await server.close()


def robot_program(partition: int = 1) -> dict[str, str]:
    source = (EXAMPLES / "robot" / "conveyor_to_cnc1.aml").read_text()
    text = compile_source(source, "LOAD1", partition).to_text()
    return {"program": "load1.rec", "text": text}


async def test_status_info_and_private_files(api: Api) -> None:
    info = await api.call("server.info")
    assert info["mode"] == "attached" and "robot.download" in info["methods"]
    status = await api.call("cell.status")
    assert set(status) >= {"cell", "machines", "orders", "parts", "alarms", "events"}
    assert set(status["machines"]) >= {"robot", "cnc1", "cnc2"}
    for name in ("api-token", "api.sock", "journal.sqlite3", "mailbox.sqlite3"):
        mode = stat.S_IMODE(os.stat((api.directory / name).resolve()).st_mode)
        assert mode == 0o600, f"{name} is {oct(mode)}"


async def test_socket_appears_only_when_it_listens(tmp_path: Path) -> None:
    """A client that sees ``api.sock`` can connect: the file is renamed into place once the
    socket listens (a command that saw it and was refused took a running server for none)."""
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        assert rig.controller is not None
        path = rig.directory / "api.sock"
        seen: list[str] = []
        stop = threading.Event()

        def watch() -> None:  # a client in another thread, connecting on first sight
            while not os.path.exists(path):
                if stop.is_set():
                    return
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as client:
                try:
                    client.connect(str(path))
                    seen.append("connected")
                except OSError as e:
                    seen.append(f"refused: {e}")

        watcher = asyncio.create_task(asyncio.to_thread(watch))
        server = ApiServer(AttachedCell(rig.controller), rig.directory)
        await server.start()
        try:
            async with asyncio.timeout(10):
                await watcher
            assert seen == ["connected"]
            assert sorted(p.name for p in rig.directory.glob("api.sock*")) == ["api.sock"]
        finally:
            stop.set()
            await server.close()


async def test_orders_submit_list_cancel(api: Api) -> None:
    await api.call("cell.pause")
    posted = await api.call("orders.submit", {"part_type": "wax-robot-base", "qty": 2, "id": "C1"})
    assert posted["new"] and "order C1 posted" in posted["message"]
    again = await api.call("orders.submit", {"part_type": "wax-robot-base", "qty": 2, "id": "C1"})
    assert not again["new"]
    with pytest.raises(UsageError, match="unknown part type 'nope'"):
        await api.call("orders.submit", {"part_type": "nope"})
    await api.rig.wait_for(lambda: api.rig.order_state("C1") == "accepted", "C1 accepted")
    listed = await api.call("orders.list", {"states": ["accepted"]})
    assert [o["id"] for o in listed] == ["C1"] and listed[0]["parts"] == {"waiting": 2}
    cancelled = await api.call("orders.cancel", {"id": "C1"})
    assert "cancelled" in cancelled["message"]
    assert api.rig.order_state("C1") == "cancelled"
    assert {p.status for p in api.rig.journal.parts(order_id="C1")} == {"cancelled"}
    with pytest.raises(UsageError, match="only an order that has not started"):
        await api.call("orders.cancel", {"id": "C1"})
    await api.call("cell.resume")


async def test_a_started_order_cannot_be_cancelled(api: Api) -> None:
    api.rig.post("wax-robot-base", 1, "S1")
    await api.rig.wait_for(lambda: api.rig.journal.steps(), "a step started")
    # Refused by the journal (a step has run) or, once the order is in progress, by its
    # state: whichever the controller has reached by now.
    refusal = r"has started \(\d+ step\(s\) run\)|is in-progress: only an order that has not"
    with pytest.raises(UsageError, match=refusal):
        await api.call("orders.cancel", {"id": "S1"})
    assert api.rig.order_state("S1") != "cancelled"
    assert "cancelled" not in {p.status for p in api.rig.journal.parts(order_id="S1")}


async def test_pause_holds_new_work_and_resume_runs_it(api: Api) -> None:
    paused = await api.call("cell.pause")
    assert "paused" in paused["message"]
    await api.call("orders.submit", {"part_type": "wax-robot-base", "id": "P1"})
    await api.rig.wait_for(lambda: api.rig.order_state("P1") == "accepted", "P1 accepted")
    # Ten monitor rounds go by (each tells the listeners): nothing starts.
    controller = api.rig.controller
    assert controller is not None
    rounds: list[int] = []
    controller.listeners.append(lambda: rounds.append(1))
    await api.rig.wait_for(lambda: len(rounds) >= 10, "ten rounds while paused")
    assert (await api.call("cell.status"))["cell"]["paused"] is True
    assert not api.rig.journal.steps()
    await api.call("cell.resume")
    await api.rig.wait_for(lambda: api.rig.journal.steps(), "a step after resume")


async def test_alarms_list_and_clear(api: Api) -> None:
    api.rig.cell.plc.set_fault("estop", None)
    alarm = await api.rig.wait_for(lambda: api.rig.alarms("plc", "estop"), "estop alarm")
    api.rig.cell.plc.clear_fault("estop")
    listed = await api.call("alarms.list")
    assert alarm[0].id in [a["id"] for a in listed]
    cleared = await api.call("alarms.clear", {"id": alarm[0].id})
    assert f"alarm {alarm[0].id} cleared" in cleared["message"]
    assert alarm[0].id not in [a["id"] for a in await api.call("alarms.list")]
    assert alarm[0].id in [a["id"] for a in await api.call("alarms.list", {"all": True})]
    with pytest.raises(UsageError):
        await api.call("alarms.clear", {"id": 9999})


async def test_alarms_ack_shelve_history_and_a_wrong_token_acks_nothing(api: Api) -> None:
    rig = api.rig
    rig.cell.plc.set_fault("estop", None)
    [alarm] = await rig.wait_for(lambda: rig.alarms("plc", "estop"), "estop alarm")
    [listed] = [a for a in await api.call("alarms.list") if a["id"] == alarm.id]
    assert (listed["priority"], listed["acked"], listed["returned"]) == ("high", None, None)
    # The fault goes away: the monitor marks the alarm returned to normal; it stays open.
    rig.cell.plc.clear_fault("estop")
    await rig.wait_for(lambda: rig.journal.get_alarm(alarm.id).returned is not None, "RTN")
    # A wrong token does not reach the method table at all.
    with pytest.raises(InvalidStatus):
        async with connect(
            f"ws://127.0.0.1:{api.port}/websocket",
            additional_headers={"Authorization": "Bearer wrong"},
        ):
            pass
    assert rig.journal.get_alarm(alarm.id).acked is None
    acked = await api.call("alarms.ack", {"id": alarm.id})
    assert f"alarm {alarm.id} acknowledged" in acked["message"]
    assert acked["alarm"]["acked"] is not None and acked["alarm"]["state"] == "active"
    # Who did it is the caller the audit names (the cell's own token here), not a role.
    assert acked["alarm"]["acked_by"] == "token:default", acked["alarm"]
    again = await api.call("alarms.ack", {"id": alarm.id})
    assert "already acknowledged" in again["message"]

    # The same from the shell, through the running controller's socket.
    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        command = [*CELLCTL, "--cell", str(api.directory), "alarm", *args]
        return subprocess.run(command, capture_output=True, text=True, timeout=60)

    shell = await asyncio.to_thread(cli, "ack", str(alarm.id))
    assert shell.returncode == 0 and "already acknowledged" in shell.stdout, shell.stderr
    listed_cli = await asyncio.to_thread(cli, "list")
    words = listed_cli.stdout.split()
    assert "acked," in words and "returned" in words and "UNACKED" not in listed_cli.stdout
    refused = await asyncio.to_thread(cli, "shelve", str(alarm.id), "--for", "9h")
    assert refused.returncode == 2 and "at most 8h" in refused.stderr
    shelved_cli = await asyncio.to_thread(cli, "shelve", str(alarm.id), "--for", "1h30m")
    assert f"alarm {alarm.id} shelved for 1h 30m" in shelved_cli.stdout, shelved_cli.stderr
    shelved = await api.call("alarms.shelve", {"id": alarm.id, "seconds": 1800})
    assert "shelved for 30m" in shelved["message"] and shelved["alarm"]["shelved_until"]
    assert shelved["alarm"]["shelved_by"] == "token:default", shelved["alarm"]
    for bad in ({"id": alarm.id, "seconds": 8 * 3600 + 1}, {"id": alarm.id, "seconds": 0}):
        with pytest.raises(UsageError, match="seconds"):
            await api.call("alarms.shelve", bad)
    with pytest.raises(UsageError, match="priority"):
        await api.call("alarms.history", {"priority": "urgent"})
    await api.call("alarms.clear", {"id": alarm.id})
    history = await api.call("alarms.history", {"machine": "plc", "priority": "high"})
    assert [a["id"] for a in history] == [alarm.id] and history[0]["state"] == "cleared"
    assert history[0]["cleared_by"] == "token:default", history[0]
    assert await api.call("alarms.history", {"machine": "cnc1"}) == []
    assert await api.call("alarms.history", {"since": alarm.raised + 3600}) == []
    history_cli = await asyncio.to_thread(
        cli, "history", "--machine", "plc", "--priority", "high", "--since", "1h", "--json"
    )
    assert [a["id"] for a in json.loads(history_cli.stdout)] == [alarm.id], history_cli.stderr
    table = await asyncio.to_thread(cli, "history", "--priority", "low")
    assert table.returncode == 0 and "no alarms" in table.stdout
    bad = await asyncio.to_thread(cli, "history", "--since", "yesterday")
    assert bad.returncode == 2 and "--since" in bad.stderr


async def test_parts_release_and_scrap(api: Api) -> None:
    await api.call("cell.pause")
    api.rig.post("wax-robot-base", 2, "H1")
    await api.rig.wait_for(lambda: len(api.rig.journal.parts(order_id="H1")) == 2, "parts")
    first, second = api.rig.journal.parts(order_id="H1")
    api.rig.journal.hold_part(first.id, "looked damaged")
    api.rig.journal.hold_part(second.id, "looked damaged")
    held = await api.call("parts.list", {"statuses": ["held"]})
    assert {p["id"] for p in held} == {first.id, second.id}
    released = await api.call("parts.release", {"id": first.id})
    assert f"part {first.id} released" in released["message"]
    scrapped = await api.call("parts.scrap", {"id": second.id, "reason": "cracked"})
    assert scrapped["message"] == f"part {second.id} scrapped"
    statuses = {p.id: p.status for p in api.rig.journal.parts(order_id="H1")}
    assert statuses == {first.id: "waiting", second.id: "scrapped"}
    await api.call("cell.resume")


async def test_manual_functions_only_out_of_automatic_service(api: Api) -> None:
    # Status is an observation: allowed in automatic service.
    status = await api.call("robot.status", {"machine": "robot"})
    assert status["state_text"] and "partitions" in status
    with pytest.raises(MachineInUse, match="in automatic service: take it out first"):
        await api.call("robot.home", {"machine": "robot"})
    again = await api.call("machines.return_to_service", {"machine": "robot"})
    assert again["message"].startswith("robot is already in automatic service"), again
    out = await api.call("machines.out_of_service", {"machine": "robot", "reason": "teach"})
    assert "out of automatic service" in out["message"]
    # Said again without a reason: the first one stays, and so says the answer.
    again = await api.call("machines.out_of_service", {"machine": "robot"})
    assert again["message"] == (
        "robot is already out of automatic service (taken out by the operator: teach)"
    )
    assert api.rig.journal.machines_out_of_service()["robot"].endswith(": teach")
    await api.rig.wait_for(lambda: api.rig.controller and not api.rig.controller._busy(), "idle")
    assert (await api.call("robot.home"))["message"] == "Home"
    down = await api.call("robot.download", {"machine": "robot", "partition": 4, **robot_program()})
    assert down["message"] == "Download was correct"
    status = await api.call("robot.status", {"machine": "robot"})
    assert status["partitions"]["4"] == "LOAD1"
    with pytest.raises(DeviceError, match="partition empty"):
        await api.call("robot.go", {"machine": "robot", "partition": 5})
    io = await api.call("robot.io")
    assert len(io["inputs"]) == 16
    assert "Reject status" in (await api.call("robot.reject"))["message"]
    assert (await api.call("robot.reset"))["message"] == "Errors reset"
    back = await api.call("machines.return_to_service", {"machine": "robot"})
    assert "back in automatic service" in back["message"]
    rows = await api.call("traffic.tail", {"machine": "robot", "limit": 5})
    assert len(rows) == 5 and {r["dir"] for r in rows} <= {">>", "<<"}


async def test_mill_menu_by_hand_while_the_cell_runs(api: Api) -> None:
    await api.call("machines.out_of_service", {"machine": "cnc2"})
    api.rig.post("wax-robot-base", 1, "M1")
    await api.rig.wait_for(
        lambda: any(s.machine == "cnc1" and s.state == "finished" for s in api.rig.journal.steps()),
        "cnc1 cut while cnc2 is out",
    )
    assert (await api.call("mill.status", {"machine": "cnc2"}))["state"] == 2
    ended = await api.call("mill.end", {"machine": "cnc2"})
    assert ended["message"] == "Ending was correct"
    mill = api.rig.cell.mills["cnc2"]
    mill.select(mill.auto_mode)  # the operator selects the link mode on the panel: READY
    setup = api.directory / "programs" / "cnc2_setup.dyn"
    params = {"machine": "cnc2", "program": setup.name, "text": setup.read_text(), "force": True}
    init = await api.call("mill.init", params)
    assert init["message"] == "Initializing was correct"
    back = await api.call("machines.return_to_service", {"machine": "cnc2"})
    assert "back in automatic service" in back["message"]
    await api.rig.wait_for(lambda: api.rig.order_state("M1") == "done", "M1 done", timeout=60)
    assert not api.rig.alarms() and not api.rig.cut_twice()


async def test_emergency_stop_halts_and_holds(api: Api) -> None:
    api.rig.post("wax-robot-base", 1, "E1")
    await api.rig.wait_for(lambda: api.rig.open_steps("machine"), "a cut in flight", timeout=60)
    mills = api.rig.cell.mills
    before = {name: len(m.runs) for name, m in mills.items()}
    stopped = await api.call("cell.estop", {"reason": "guard opened"})
    assert "emergency stop: guard opened" in stopped["message"]
    status = await api.call("cell.status")
    assert status["cell"]["paused"] is True
    assert any(a["code"] == "estop" and a["machine"] == "cell" for a in status["alarms"])
    held = api.rig.held_parts()
    assert held and "emergency stop" in held[0].note
    # Every mill got END (back in manual): the idle one at once, the cutting one once its
    # block ended (a block whose last lines were still on the line is waited out too: an END
    # arriving as it starts would be lost).
    assert all("END" in [r.outcome for r in m.runs[before[n] :]] for n, m in mills.items())
    # Not resumed while the stop's alarm is open: nothing moves a mill before it is cleared.
    with pytest.raises(MachineInUse, match=r"the emergency stop's alarm \d+ is not cleared"):
        await api.call("cell.resume")
    assert (await api.call("cell.status"))["cell"]["paused"] is True
    # The operator's way back: ready the mills at their panels (the emulators' operator
    # does), clear the alarms, scrap the part cut short, resume: the mills are initialized
    # anew (not before the resume: no setup moves a mill while the stop is dealt with).
    await api.rig.wait_for(lambda: all(m.display == "READY" for m in mills.values()), "READY")
    for alarm in status["alarms"]:
        await api.call("alarms.clear", {"id": alarm["id"]})
    for part in held:
        # Cut short in the mill: scrapped only once the operator says it is out of the vise
        # (the cell loads the mill again at once).
        why = {"id": part.id, "reason": "cut short by the stop"}
        with pytest.raises(UsageError, match=f"part {part.id} may be in {part.location}: take"):
            await api.call("parts.scrap", why)
        assert api.rig.journal.get_part(part.id).status == "held"
        scrapped = await api.call("parts.scrap", {**why, "taken_out": True})
        assert f"taken out of {part.location}, which takes parts again" in scrapped["message"]
    assert (await api.call("cell.resume"))["message"] == "resumed"
    controller = api.rig.controller
    assert controller is not None
    for name in mills:
        await api.rig.wait_for(
            lambda name=name: controller.machines[name].state == "Initialized",
            f"{name} initialized again",
        )
        assert controller.recovery.usable(name)


async def test_subscription_pushes_changes(api: Api) -> None:
    """A real batch: every status read fits the model, the machines' conditions and steps
    are fields, and the pushed differences, applied, give the status the API answers."""
    updates: list[dict[str, Any]] = []
    snapshot = await api.client.subscribe(updates.append)
    assert "machines" in snapshot
    await api.call("orders.submit", {"part_type": "wax-robot-base", "id": "U1"})
    await api.rig.wait_for(
        lambda: any(any(o["id"] == "U1" for o in u.get("orders", [])) for u in updates),
        "an update with order U1",
    )
    # The controller's event for the order is pushed too, as a new event (not the snapshot).
    assert not any("order U1 accepted" in e["text"] for e in snapshot["events"])
    await api.rig.wait_for(
        lambda: any(
            e["text"].startswith("order U1 accepted") for u in updates for e in u.get("events", [])
        ),
        "the event 'order U1 accepted', pushed",
    )
    # While the batch runs: the robot and a mill busy, each with its step as fields.
    seen: set[tuple[str, str, str]] = set()
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 60
    while api.rig.order_state("U1") != "done":
        assert loop.time() < deadline, f"U1 not done: {api.rig.describe()}"
        status = CellStatus.model_validate(await api.call("cell.status"))
        for m in status.machines.values():
            if m.step is not None and m.step.what is not StepKind.MANUAL:
                assert m.condition is Condition.BUSY and m.step.part_id
                assert m.part == m.step.part_id
                seen.add((m.family, m.step.what.value, m.condition.value))
            if m.progress is not None and m.progress.blocks:
                assert m.progress.unit == "bytes" and 0 <= m.progress.fraction <= 1
        await asyncio.sleep(0.01)
    assert ("robot", "transfer", "busy") in seen and ("mill", "machine", "busy") in seen, seen
    # Out of service: the machine's condition says so, in one update of that machine alone.
    await api.call("machines.out_of_service", {"machine": "cnc2", "reason": "new cutter"})
    status = CellStatus.model_validate(await api.call("cell.status"))
    assert status.machines["cnc2"].condition is Condition.OUT_OF_SERVICE
    assert "new cutter" in status.machines["cnc2"].out_reason
    await api.rig.wait_for(
        lambda: any(
            u.get("machines", {}).get("cnc2", {}).get("condition") == "out-of-service"
            for u in updates
        ),
        "cnc2 out of service, pushed",
    )
    # What the client holds (the first status and every difference) is what the API says.
    while True:
        held = snapshot
        for u in list(updates):
            held = apply_update_json(held, u)
        now = CellStatus.model_validate(await api.call("cell.status"))
        if CellStatus.model_validate(held).stable() == now.stable():
            break
        assert loop.time() < deadline + 30, "the pushed differences never gave the status"
        await asyncio.sleep(0.05)
    await api.call("machines.return_to_service", {"machine": "cnc2"})


@pytest.mark.parametrize(
    ("method", "params", "error", "message"),
    [
        ("nope.nothing", {}, UsageError, "no method 'nope.nothing'"),
        ("orders.submit", {"part_type": "wax-robot-base", "qty": 0}, UsageError, "qty"),
        ("orders.submit", {"part_type": "x", "colour": "red"}, UsageError, "colour"),
        ("alarms.clear", {"id": "three"}, UsageError, "id"),
        ("robot.go", {"machine": "robot", "partition": 6}, UsageError, "1 to 5"),
        ("robot.status", {"machine": "cnc1"}, UsageError, "is a mill, not a robot"),
        ("mill.status", {"machine": "cnc9"}, UsageError, "unknown mill 'cnc9'"),
        ("robot.download", {"partition": 1, "program": "x.rec", "text": "NOT A RECORD"},
         UsageError, "x.rec, line 1: bad hex digit"),
        ("traffic.tail", {"machine": "robot", "limit": -1}, UsageError, "limit"),
    ],
)  # fmt: skip
async def test_bad_parameters_are_refused_with_the_cli_error(
    standalone: tuple[RemoteCell, LocalCell],
    method: str,
    params: dict[str, Any],
    error: type[Exception],
    message: str,
) -> None:
    client, access = standalone
    # Each machine's link is open (a mill's status is read from its lines, no byte sent) and
    # nothing else talks to them (no controller polls): the trace shows any byte a refused
    # call sends.
    await client.call("robot.status", {"machine": "robot"})
    for mill in ("cnc1", "cnc2"):
        await client.call("mill.status", {"machine": mill})
    sent_before = [e for e in access.traffic_log.entries if e[2] == SENT]
    assert "robot" in {e[1] for e in sent_before}
    with pytest.raises(error, match=message):
        await client.call(method, params)
    sent_after = [e for e in access.traffic_log.entries if e[2] == SENT]
    assert sent_after == sent_before, f"bytes reached a machine: {sent_after[len(sent_before) :]}"


@pytest.fixture
async def standalone(tmp_path: Path) -> AsyncIterator[tuple[RemoteCell, LocalCell]]:
    """The API served without a controller, on the emulated cell's machines."""
    async with (
        CellRig(tmp_path / "cell") as rig,
        LocalCell(rig.directory, cell_refs(rig.directory)) as access,
    ):
        server = ApiServer(access, rig.directory)
        await server.start()
        client = await attach(rig.directory)
        try:
            yield client, access
        finally:
            await client.close()
            await server.close()


async def raw(api: Api, **kwargs: Any) -> Any:
    token = (api.directory / "api-token").read_text().strip()
    headers = {"Authorization": f"Bearer {token}"}
    return await unix_connect(
        (api.directory / "api.sock").resolve(),
        "ws://localhost/websocket",
        additional_headers=headers,
        **kwargs,
    )


async def test_malformed_and_oversized_frames(api: Api) -> None:
    async with await raw(api, max_size=None) as ws:
        await ws.send("{not json")
        assert json.loads(await ws.recv())["error"]["code"] == -32700
        await ws.send(json.dumps({"id": 1, "method": "cell.status"}))
        assert json.loads(await ws.recv())["error"]["code"] == -32600
        await ws.send(b"\x00\x01")
        assert json.loads(await ws.recv())["error"]["code"] == -32600
        await ws.send(
            json.dumps({"jsonrpc": "2.0", "id": 2, "method": "cell.status", "params": [1]})
        )
        reply = json.loads(await ws.recv())
        assert reply["id"] == 2 and reply["error"]["data"]["type"] == "UsageError"
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": 3, "method": "server.info"}))
        assert json.loads(await ws.recv())["result"]["mode"] == "attached"
        with pytest.raises(ConnectionClosed):
            await ws.send("x" * (9 * 1024 * 1024))
            await ws.recv()
    assert (await api.call("server.info"))["mode"] == "attached"  # the server lives on


async def test_tokens_on_tcp_and_the_socket(api: Api) -> None:
    url = f"http://127.0.0.1:{api.port}"
    token = (api.directory / "api-token").read_text().strip()

    def get(path: str, token: str | None) -> tuple[int, Any]:
        request = urllib.request.Request(url + path)
        if token is not None:
            request.add_header("Authorization", f"Bearer {token}")
        try:
            with urllib.request.urlopen(request, timeout=10) as response:
                return response.status, json.loads(response.read())
        except urllib.error.HTTPError as e:
            return e.code, json.loads(e.read() or b"null")

    status, body = await asyncio.to_thread(get, "/api/status", token)
    assert status == 200 and "robot" in body["machines"]
    for wrong in (None, "wrong", token + "x"):
        status, body = await asyncio.to_thread(get, "/api/status", wrong)
        assert status == 401 and "machines" not in json.dumps(body)
    status, schema = await asyncio.to_thread(get, "/api/schema", token)
    assert status == 200 and schema["status"] == CellStatus.model_json_schema()
    status, body = await asyncio.to_thread(get, "/api/status", token)
    CellStatus.model_validate(body)  # what /api/status answers fits the schema served
    for wrong in (None, "wrong"):
        status, body = await asyncio.to_thread(get, "/api/schema", wrong)
        assert status == 401 and "properties" not in json.dumps(body)
    status, body = await asyncio.to_thread(get, "/api/traffic/robot?limit=3", token)
    assert status == 200 and len(body) <= 3
    for all_ in ("1", "true", "yes", "0", "false", "no"):
        status, body = await asyncio.to_thread(get, f"/api/alarms?all={all_}", token)
        assert status == 200 and isinstance(body, list), (all_, body)
    status, body = await asyncio.to_thread(get, "/api/alarms?all=sometimes", token)
    assert status == 400 and "all" in body["error"]["message"], body
    for headers in ({}, {"Authorization": "Bearer wrong"}):
        with pytest.raises(InvalidStatus):
            async with connect(f"ws://127.0.0.1:{api.port}/websocket", additional_headers=headers):
                pass
    with pytest.raises(InvalidStatus):  # a page of another site cannot drive the cell
        async with connect(
            f"ws://127.0.0.1:{api.port}/websocket",
            additional_headers={"Authorization": f"Bearer {token}"},
            origin="http://evil.example",  # type: ignore[arg-type]
        ):
            pass
    with pytest.raises(AccessDenied):
        await RemoteCell.connect(token="wrong", socket_path=api.directory / "api.sock")
    async with await RemoteCell.connect(token=token, url=f"ws://127.0.0.1:{api.port}") as c:
        assert (await c.call("server.info"))["mode"] == "attached"


async def test_listen_on_a_foreign_address_is_refused(api: Api) -> None:
    assert api.rig.controller is not None
    with pytest.raises(UsageError, match="not a loopback address"):
        ApiServer(AttachedCell(api.rig.controller), api.directory, listen="192.0.2.1:7125")


async def test_a_client_leaving_mid_download_leaves_the_machine_consistent(api: Api) -> None:
    await api.call("machines.out_of_service", {"machine": "robot"})
    await api.rig.wait_for(lambda: api.rig.controller and not api.rig.controller._busy(), "idle")
    ws = await raw(api)
    request = {
        "jsonrpc": "2.0",
        "id": 7,
        "method": "robot.download",
        "params": {"machine": "robot", "partition": 5, **robot_program()},
    }
    await ws.send(json.dumps(request))
    await ws.recv()  # the first progress notification: the download is under way
    await ws.close()
    # The call runs to its end: the partition holds the program, and the robot answers.
    await api.rig.wait_for(
        lambda: api.rig.controller and "robot" not in api.rig.controller.manual_use, "done"
    )
    status = await api.call("robot.status")
    assert status["partitions"]["5"] == "LOAD1"
    assert (await api.call("robot.go", {"partition": 5}))["message"] == "Started Cycle"


def test_the_docs_list_every_method_as_served() -> None:
    from cellctl.service.methods import reference_table

    docs = (Path(__file__).resolve().parent.parent / "docs" / "api.md").read_text()
    assert reference_table() in docs
    assert docs.count("| method | parameters") == 1  # and no older copy beside it


async def test_a_browser_gets_a_oneshot_token_and_every_answer_a_csp(api: Api) -> None:
    url = f"http://127.0.0.1:{api.port}"
    token = (api.directory / "api-token").read_text().strip()

    def get(path: str, auth: str | None) -> tuple[int, Any, Any]:
        request = urllib.request.Request(url + path)
        if auth:
            request.add_header("Authorization", f"Bearer {auth}")
        try:
            with urllib.request.urlopen(request, timeout=10) as response:
                return response.status, response.headers, json.loads(response.read())
        except urllib.error.HTTPError as e:
            return e.code, e.headers, None

    status, headers, _ = await asyncio.to_thread(get, "/access/oneshot_token", None)
    assert status == 401 and "default-src 'none'" in headers["Content-Security-Policy"]
    status, headers, body = await asyncio.to_thread(get, "/access/oneshot_token", token)
    assert status == 200 and "script-src 'self'" in headers["Content-Security-Policy"]
    oneshot = body["token"]
    async with connect(f"ws://127.0.0.1:{api.port}/websocket?token={oneshot}") as ws:
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": 1, "method": "server.info"}))
        assert json.loads(await ws.recv())["result"]["mode"] == "attached"
    with pytest.raises(InvalidStatus):  # used once: gone
        async with connect(f"ws://127.0.0.1:{api.port}/websocket?token={oneshot}"):
            pass
