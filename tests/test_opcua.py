"""The cell's OPC UA server as a SCADA client meets it: an asyncua client on a signed and
encrypted channel, against the emulated cell and a real controller started by
``run_controller`` (what ``cellctl run`` runs) with ``[opcua]`` in cell.toml."""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
import socket
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.common.node import Node
from asyncua.crypto import cert_gen
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from asyncua.ua.uaerrors import BadIdentityTokenRejected, BadUserAccessDenied, UaError
from click.testing import CliRunner
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cellctl.cell.config import OpcuaTable, check_cell
from cellctl.errors import UsageError
from cellctl.factory.opcua import NAMESPACE, OpcuaServer
from cellctl.factory.opcua.figures import MACHINE_CONDITIONS, SIGNAL_COLORS
from cellctl.factory.opcua.users import check_password, hash_password, load_entries, load_users
from cellctl.kinds import Condition
from cellctl.service.access import LocalCell
from cellctl.service.client import attach
from cellctl.testing.rig import CellRig
from cellctl.ui.cell_cli import run_controller
from cellctl.ui.cli import main as cli_main
from tests.conftest import until

CLIENT_URI = "urn:cellctl:tests:client"
SIGN_AND_ENCRYPT = ua.MessageSecurityMode.SignAndEncrypt
UINT32 = ua.VariantType.UInt32


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def client_cert(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    """A client application certificate, as UaExpert makes one for itself."""
    folder = tmp_path_factory.mktemp("client")
    key = cert_gen.generate_private_key()
    cert = cert_gen.generate_self_signed_app_certificate(
        key,
        "cellctl tests",
        {},
        [x509.UniformResourceIdentifier(CLIENT_URI), x509.DNSName(socket.gethostname())],
        extended=[ExtendedKeyUsageOID.CLIENT_AUTH],
    )
    (folder / "key.pem").write_bytes(cert_gen.dump_private_key_as_pem(key))
    (folder / "cert.der").write_bytes(cert.public_bytes(Encoding.DER))
    return str(folder / "cert.der"), str(folder / "key.pem")


@contextlib.asynccontextmanager
async def session(
    url: str,
    cell: Path,
    cert: tuple[str, str],
    user: str | None = None,
    password: str | None = None,
    mode: ua.MessageSecurityMode = SIGN_AND_ENCRYPT,
) -> AsyncIterator[Client]:
    # The client's watchdog reads the server's state every watchdog_intervall and gives the
    # connection up if that read takes longer: 1 s by default, which a server sharing a
    # loaded box with its cell (and five other test workers) can take.
    client = Client(url, timeout=5, watchdog_intervall=5)
    client.application_uri = CLIENT_URI
    server_cert = cell / "state" / "opcua" / "server-cert.der"
    await client.set_security(
        SecurityPolicyBasic256Sha256,
        cert[0],
        cert[1],
        server_certificate=str(server_cert),
        mode=mode,
    )
    if user is not None:
        client.set_user(user)
        client.set_password(password or "")
    async with client:
        yield client


def add_user(cell: Path, name: str, password: str, role: str = "operator") -> None:
    result = CliRunner().invoke(
        cli_main,
        ["--cell", str(cell), "opcua", "adduser", name, "--role", role],
        input=f"{password}\n{password}\n",
    )
    assert result.exit_code == 0, result.output


class Seen:
    """What a subscription delivered: data changes and events."""

    def __init__(self) -> None:
        self.values: list[Any] = []
        self.events: list[Any] = []

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.values.append(val)

    def event_notification(self, event: Any) -> None:
        self.events.append(event)


async def _a_viewer_cannot_order(
    url: str, cell: Path, cert: tuple[str, str], cell_id: ua.NodeId, submit_id: ua.NodeId
) -> None:
    """A user with the viewer role reads, but SubmitOrder is refused with the role lacked,
    and the refusal is in the audit trail under the user's name."""
    from cellctl.service.audit import AuditLog

    async with session(url, cell, cert, "vera", "vera-pass") as vera:
        refused = await call_raw(vera, cell_id, submit_id, "wax-robot-base", ua.Variant(1, UINT32))
    assert refused.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
    words = refused.InputArgumentDiagnosticInfos[0].AdditionalInfo
    assert "vera is a viewer: orders.submit needs the operator role" in words
    async with session(url, cell, cert, "vera", "vera-pass") as vera:
        idx = await vera.get_namespace_index(NAMESPACE)
        ack = vera.get_node(ua.NodeId("Cell/AcknowledgeAlarm", idx))
        refused = await call_raw(vera, cell_id, ack.nodeid, ua.Variant(1, UINT32))
    assert refused.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
    words = refused.InputArgumentDiagnosticInfos[0].AdditionalInfo
    assert "vera is a viewer: alarms.ack needs the operator role" in words
    with AuditLog(cell) as log:
        entries = log.entries(who="vera")
    assert [(e.who, e.method) for e in entries] == [
        ("opcua:vera", "orders.submit"),
        ("opcua:vera", "alarms.ack"),
    ]
    assert all("needs the operator role" in e.result for e in entries)


async def call_raw(client: Client, cell: ua.NodeId, method: ua.NodeId, *args: Any) -> Any:
    """One method call whose Bad status is returned, not raised (to read its words)."""
    request = ua.CallMethodRequest()
    request.ObjectId, request.MethodId = cell, method
    request.InputArguments = [a if isinstance(a, ua.Variant) else ua.Variant(a) for a in args]
    [result] = await client.uaclient.call([request])
    return result


async def test_a_user_watches_and_orders_an_anonymous_reader_cannot_act(
    tmp_path: Path, client_cert: tuple[str, str], capfd: pytest.CaptureFixture[str]
) -> None:
    port = free_port()
    url = f"opc.tcp://127.0.0.1:{port}"
    # Cuts of a few seconds: a subscription is sent the latest value of each publishing
    # interval, and a cut shorter than a loaded box's interval would never be seen machining.
    async with CellRig(tmp_path / "cell", time_scale=200.0) as rig:
        cell = rig.directory
        add_user(cell, "alice", "correct horse")
        add_user(cell, "vera", "vera-pass", role="viewer")
        assert (cell / "opcua-users.toml").stat().st_mode & 0o777 == 0o600
        with (cell / "cell.toml").open("a") as f:
            f.write(
                f'\n[opcua]\nlisten = "{url}"\nusers = "opcua-users.toml"\nanonymous_read = true\n'
            )
        stop = asyncio.Event()
        run = asyncio.create_task(run_controller(cell, live=False, until_idle=False, stop=stop))
        try:
            await _scenario(rig, url, client_cert, run)
        finally:
            stop.set()
            async with asyncio.timeout(30):
                await run
    out = capfd.readouterr().out
    assert f"OPC UA on {url} (Basic256Sha256 Sign, SignAndEncrypt" in out  # as `cellctl run` says
    assert "OPC UA: login refused for user 'mallory' from 127.0.0.1" in out


async def _scenario(rig: CellRig, url: str, cert: tuple[str, str], run: asyncio.Task[Any]) -> None:
    cell = rig.directory

    async def serving() -> bool:
        if run.done():
            run.result()
        with contextlib.suppress(OSError, UaError, TimeoutError):
            async with session(url, cell, cert, "alice", "correct horse"):
                return True
        return False

    await until(serving, "the OPC UA server")
    key = cell / "state" / "opcua" / "server-key.pem"
    assert key.stat().st_mode & 0o777 == 0o600

    # Only signed and encrypted endpoints; a client with no security finds none.
    endpoints = await Client(url, timeout=5).connect_and_get_server_endpoints()
    assert {(e.SecurityPolicyUri.rsplit("#")[-1], e.SecurityMode) for e in endpoints} == {
        ("Basic256Sha256", ua.MessageSecurityMode.Sign),
        ("Basic256Sha256", SIGN_AND_ENCRYPT),
    }

    # A wrong password, and a name nobody added, are refused.
    for user, password in (("alice", "wrong"), ("mallory", "correct horse")):
        with pytest.raises(BadUserAccessDenied):
            async with session(url, cell, cert, user, password):
                pass

    async with session(url, cell, cert, "alice", "correct horse") as alice:
        idx = await alice.get_namespace_index(NAMESPACE)
        objects = alice.nodes.objects
        machines = await objects.get_child(f"{idx}:Machines")
        names = {(await n.read_browse_name()).Name for n in await machines.get_children()}
        assert names == {"robot", "cnc1", "cnc2"}
        cnc1 = await machines.get_child(f"{idx}:cnc1")
        maker = await cnc1.get_child([f"{idx}:Identification", f"{idx}:Manufacturer"])
        assert await maker.read_value() == "Dyna"
        state = await cnc1.get_child([f"{idx}:Monitoring", f"{idx}:MachineState"])
        program = await cnc1.get_child([f"{idx}:Production", f"{idx}:ActiveProgram"])
        cell_node = await objects.get_child(f"{idx}:Cell")
        submit = await cell_node.get_child(f"{idx}:SubmitOrder")
        clear = await cell_node.get_child(f"{idx}:ClearAlarm")

        seen = Seen()
        subscription = await alice.create_subscription(20, seen)
        await subscription.subscribe_data_change(state)
        await until(_async(lambda: seen.values), "the first value of cnc1's state")

        await _methods_take_only_their_declared_arguments(alice, cell_node, submit, clear, rig)
        await _a_viewer_cannot_order(url, cell, cert, cell_node.nodeid, submit.nodeid)
        order_id = await cell_node.call_method(
            submit,
            "wax-robot-base",
            ua.Variant(1, ua.VariantType.UInt32),
            ua.Variant(0, ua.VariantType.Int32),
        )
        assert rig.mailbox.get_order(order_id).part_type == "wax-robot-base"
        await until(_async(lambda: "machining" in seen.values), "cnc1 machining, pushed")
        name = await program.get_child(f"{idx}:Name")
        assert (await name.read_value()).startswith("robot_base")
        order_state = await cell_node.get_child(
            [f"{idx}:Orders", f"{idx}:{order_id}", f"{idx}:State"]
        )
        await until(lambda: _equals(order_state, "done"), "the order done, as the Orders node says")
        # PartCounts counts parts (OPC 40501), written with the order's state: the one part
        # made, on each machine it went through, not the robot's three transfers.
        for machine in ("robot", "cnc1", "cnc2"):
            good = await machines.get_child(
                [f"{idx}:{machine}", f"{idx}:Production", f"{idx}:PartCounts", f"{idx}:Good"]
            )
            assert await good.read_value() == 1, machine
        await _condition_follows_service(alice, idx, cell)

        refused = await call_raw(
            alice, cell_node.nodeid, submit.nodeid, "no-such-part", ua.Variant(1, UINT32)
        )
        assert refused.StatusCode.value == ua.StatusCodes.BadInvalidArgument
        assert (
            "unknown part type 'no-such-part'"
            in refused.InputArgumentDiagnosticInfos[0].AdditionalInfo
        )
        gone = await call_raw(
            alice, cell_node.nodeid, clear.nodeid, ua.Variant(999, ua.VariantType.UInt32)
        )
        assert gone.StatusCode.value == ua.StatusCodes.BadInvalidArgument
        assert "no alarm 999" in gone.InputArgumentDiagnosticInfos[0].AdditionalInfo

        # An alarm comes as an event; ClearAlarm clears it.
        alarm_type = await alice.nodes.base_event_type.get_child(f"{idx}:CellAlarmEventType")
        await subscription.subscribe_events(alice.nodes.server, alarm_type)
        conditions = Seen()
        condition_sub = await alice.create_subscription(20, conditions)
        await condition_sub.subscribe_events(alice.nodes.server, ua.ObjectIds.AlarmConditionType)
        rig.cell.plc.set_fault("estop")
        event = await until(
            _async(lambda: next((e for e in seen.events if e.Code == "estop" and e.Active), None)),
            "the emergency stop as an event",
        )
        assert (event.Priority, event.Acked, event.Severity) == ("high", False, 900)
        # The same alarm as an AlarmConditionType condition: active, unacknowledged, retained.
        condition = await until(
            _async(
                lambda: next(
                    (e for e in conditions.events if "emergency stop" in e.Message.Text), None
                )
            ),
            "the emergency stop as a condition",
        )

        assert condition.Retain and condition.Severity == 900
        assert getattr(condition, "ActiveState/Id") and not getattr(condition, "AckedState/Id")
        rig.cell.plc.clear_fault("estop")
        # Acknowledge (Part 9) on the condition marks it seen (an event says so); it stays
        # open until cleared. The cell's own AcknowledgeAlarm then has nothing left to do.
        alarm_node = await cell_node.get_child([f"{idx}:Alarms", f"{idx}:{event.AlarmId}"])
        async with session(url, cell, cert, "vera", "vera-pass") as vera:  # a viewer may not
            with pytest.raises(BadUserAccessDenied):
                await vera.get_node(alarm_node.nodeid).call_method(
                    ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge),
                    ua.Variant(condition.EventId, ua.VariantType.ByteString),
                    ua.LocalizedText("seen"),
                )
        assert rig.journal.get_alarm(event.AlarmId).acked is None
        await alarm_node.call_method(
            ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge),
            ua.Variant(condition.EventId, ua.VariantType.ByteString),
            ua.LocalizedText("seen"),
        )
        await until(
            _async(lambda: any(getattr(e, "AckedState/Id") for e in conditions.events)),
            "the condition acknowledged, as an event",
        )
        ack = await cell_node.get_child(f"{idx}:AcknowledgeAlarm")
        said = await cell_node.call_method(ack, ua.Variant(event.AlarmId, ua.VariantType.UInt32))
        assert f"alarm {event.AlarmId} was already acknowledged" in said
        await until(
            _async(lambda: any(e.AlarmId == event.AlarmId and e.Acked for e in seen.events)),
            "the alarm's acknowledged event",
        )
        acked = await cell_node.get_child(
            [f"{idx}:Alarms", f"{idx}:{event.AlarmId}", f"{idx}:Acked"]
        )
        await until(lambda: _equals(acked, True), "Cell/Alarms/<id>/Acked true")
        assert rig.journal.get_alarm(event.AlarmId).state == "active"
        message = await cell_node.call_method(
            clear, ua.Variant(event.AlarmId, ua.VariantType.UInt32)
        )
        assert f"alarm {event.AlarmId} cleared" in message
        await until(
            _async(lambda: any(e.AlarmId == event.AlarmId and not e.Active for e in seen.events)),
            "the alarm's cleared event",
        )
        await until(
            _async(lambda: not conditions.events[-1].Retain), "the condition no longer retained"
        )

    async with session(url, cell, cert) as anonymous:  # no user: read-only
        idx = await anonymous.get_namespace_index(NAMESPACE)
        state = anonymous.get_node(ua.NodeId("Machines/cnc1/Monitoring/MachineState", idx))
        assert isinstance(await state.read_value(), str)
        cell_node = anonymous.get_node(ua.NodeId("Cell", idx))
        submit = anonymous.get_node(ua.NodeId("Cell/SubmitOrder", idx))
        orders = len(rig.mailbox.orders())
        with pytest.raises(BadUserAccessDenied):
            await cell_node.call_method(submit, "wax-robot-base", ua.Variant(1, UINT32))
        with pytest.raises(BadUserAccessDenied):
            await state.write_value("hacked")
        assert len(rig.mailbox.orders()) == orders
        assert await state.read_value() != "hacked"


async def _condition_follows_service(client: Client, idx: int, cell: Path) -> None:
    """cnc2 taken out of service and returned (through the control API, as an operator
    would): its Condition variable and its stack light follow; cnc1's stay as they were."""

    def node(machine: str, name: str) -> Node:
        return client.get_node(ua.NodeId(f"Machines/{machine}/Monitoring/{name}", idx))

    condition, light = node("cnc2", "Condition"), node("cnc2", "StacklightColour")
    idle, out = MACHINE_CONDITIONS.index("Idle"), MACHINE_CONDITIONS.index("OutOfService")
    green, yellow = SIGNAL_COLORS.index("Green"), SIGNAL_COLORS.index("Yellow")
    await until(lambda: _equals(condition, idle), "cnc2 idle after the order")
    assert await light.read_value() == green
    async with await attach(cell) as api:
        await api.call("machines.out_of_service", {"machine": "cnc2", "reason": "new cutter"})
        await until(lambda: _equals(condition, out), "cnc2's Condition: OutOfService")
        assert await light.read_value() == yellow
        reason = await node("cnc2", "OutOfServiceReason").read_value()
        assert "new cutter" in reason
        assert await node("cnc1", "Condition").read_value() == idle
        assert await node("cnc1", "StacklightColour").read_value() == green
        await api.call("machines.return_to_service", {"machine": "cnc2"})
        await until(lambda: _equals(condition, idle), "cnc2's Condition: Idle again")
        await until(lambda: _equals(light, green), "cnc2's stack light green again")


async def _methods_take_only_their_declared_arguments(
    client: Client, cell_node: Node, submit: Node, clear: Node, rig: CellRig
) -> None:
    """A quantity as text, a fourth argument, an array, and the Cell's method called on the
    Server object: each refused with its own status and words, and no order posted."""
    orders = len(rig.mailbox.orders())
    cell, server = cell_node.nodeid, client.nodes.server.nodeid
    text_qty = await call_raw(client, cell, submit.nodeid, "wax-robot-base", "2")
    assert text_qty.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    assert [r.value for r in text_qty.InputArgumentResults] == [0, ua.StatusCodes.BadTypeMismatch]
    words = text_qty.InputArgumentDiagnosticInfos[1].AdditionalInfo
    assert "Quantity must be UInt32, not String" in words
    four = [ua.Variant(1, UINT32), ua.Variant(0, ua.VariantType.Int32), "extra"]
    too_many = await call_raw(client, cell, submit.nodeid, "wax-robot-base", *four)
    assert too_many.StatusCode.value == ua.StatusCodes.BadTooManyArguments
    wide = await call_raw(client, cell, clear.nodeid, ua.Variant(1, ua.VariantType.Int64))
    assert wide.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    array = await call_raw(client, cell, clear.nodeid, ua.Variant([1, 2], UINT32))
    assert array.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    qty = ua.Variant(1, UINT32)
    elsewhere = await call_raw(client, server, submit.nodeid, "wax-robot-base", qty)
    assert elsewhere.StatusCode.value == ua.StatusCodes.BadMethodInvalid
    assert len(rig.mailbox.orders()) == orders


def _async(fn: Callable[[], Any]) -> Callable[[], Awaitable[Any]]:
    async def wrapped() -> Any:
        return fn()

    return wrapped


async def _equals(node: Any, value: Any) -> bool:
    return bool(await node.read_value() == value)


# -- without a controller: the configuration, anonymous sessions refused, the users file --------

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell"


@pytest.fixture
def example_cell(tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    shutil.copytree(EXAMPLE, directory)
    return directory


@pytest.mark.parametrize(
    ("table", "problem"),
    [
        ('listen = "opc.tcp://192.0.2.1:4840"\nanonymous_read = true', "not a loopback address"),
        ('listen = "127.0.0.1:4840"\nanonymous_read = true', 'write "opc.tcp://HOST:PORT"'),
        ('listen = "opc.tcp://127.0.0.1:4840"', "nobody could log in"),
        (
            'listen = "opc.tcp://127.0.0.1:4840"\nusers = "nobody.toml"',
            "[opcua] users: no such file: nobody.toml (add a user: cellctl opcua adduser NAME)",
        ),
        ('listen = "opc.tcp://127.0.0.1:4840"\nanonymous_read = "yes"', "[opcua] anonymous_read"),
    ],
)
def test_opcua_table_problems(example_cell: Path, table: str, problem: str) -> None:
    with (example_cell / "cell.toml").open("a") as f:
        f.write(f"\n[opcua]\n{table}\n")
    config, problems = check_cell(example_cell)
    assert config is None
    assert any(problem in p for p in problems), problems


async def test_anonymous_is_refused_unless_allowed_and_the_users_file_must_be_private(
    example_cell: Path, client_cert: tuple[str, str]
) -> None:
    add_user(example_cell, "bob", "bob-pass")
    url = f"opc.tcp://127.0.0.1:{free_port()}"
    table = OpcuaTable(listen=url, users="opcua-users.toml")
    async with LocalCell(example_cell, {}) as access:
        server = OpcuaServer(access, table)
        await server.start()
        try:
            with pytest.raises(BadIdentityTokenRejected):
                async with session(url, example_cell, client_cert):
                    pass
            async with session(url, example_cell, client_cert, "bob", "bob-pass") as bob:
                idx = await bob.get_namespace_index(NAMESPACE)
                cell = bob.get_node(ua.NodeId("Cell/Name", idx))
                assert await cell.read_value() == "cell"
        finally:
            await server.close()
        (example_cell / "opcua-users.toml").chmod(0o644)
        with pytest.raises(UsageError, match="others may read it: chmod 600"):
            await OpcuaServer(access, table).start()


def test_a_stored_password_checks() -> None:
    stored = hash_password("correct horse")
    assert check_password(stored, "correct horse")
    assert not check_password(stored, "correct horse ")
    assert stored != hash_password("correct horse")  # salted


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=st.text(max_size=200), password=st.text(max_size=20))
def test_users_file_and_stored_passwords_give_typed_errors_only(
    tmp_path_factory: pytest.TempPathFactory, text: str, password: str
) -> None:
    path = tmp_path_factory.mktemp("users") / "users.toml"
    path.write_text(text, encoding="utf-8")
    path.chmod(0o600)
    with contextlib.suppress(UsageError):
        load_users(path)
    assert check_password(text, password) is False


_ARGUMENTS = st.lists(
    st.one_of(
        st.none(),
        st.booleans(),
        st.integers(min_value=-(2**31), max_value=2**31 - 1),
        st.floats(allow_nan=True),
        st.text(max_size=120),
        st.sampled_from(["wax-robot-base", "wax-toy-mill-table"]),
    ),
    max_size=4,
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(arguments=_ARGUMENTS)
def test_method_arguments_from_a_client_give_answers_or_refusals_in_words(
    tmp_path_factory: pytest.TempPathFactory, arguments: list[Any]
) -> None:
    cell = tmp_path_factory.mktemp("cell") / "cell"
    shutil.copytree(EXAMPLE, cell)
    variants = [ua.Variant(a) for a in arguments]

    async def call_both() -> list[Any]:
        async with LocalCell(cell, {}) as access:
            table = OpcuaTable(listen="opc.tcp://127.0.0.1:4840", anonymous_read=True)
            server = OpcuaServer(access, table)
            return [
                await server.submit_order(ua.NodeId(), *variants),
                await server.clear_alarm(ua.NodeId(), *variants),
            ]

    for result in asyncio.run(call_both()):
        if isinstance(result, ua.CallMethodResult):
            assert result.StatusCode.value in (
                ua.StatusCodes.BadInvalidArgument,
                ua.StatusCodes.BadArgumentsMissing,
                ua.StatusCodes.BadTooManyArguments,
            ), result
            assert result.InputArgumentDiagnosticInfos[0].AdditionalInfo
        else:
            assert isinstance(result, list) and isinstance(result[0].Value, str)


def test_the_condition_enumeration_names_every_condition() -> None:
    assert len(MACHINE_CONDITIONS) == len(Condition)
    words = [c.value.replace("-", "") for c in Condition]
    assert [n.lower() for n in MACHINE_CONDITIONS] == words


def test_a_new_password_keeps_the_users_role(example_cell: Path) -> None:
    add_user(example_cell, "victor", "first-pass", role="viewer")
    again = CliRunner().invoke(
        cli_main,
        ["--cell", str(example_cell), "opcua", "adduser", "victor"],
        input="second-pass\nsecond-pass\n",
    )
    assert again.exit_code == 0, again.output
    assert "user victor (viewer) has a new password" in again.output
    assert load_entries(example_cell / "opcua-users.toml")["victor"][1] == "viewer"
    # A role is changed only when given.
    add_user(example_cell, "victor", "third-pass", role="engineer")
    assert load_entries(example_cell / "opcua-users.toml")["victor"][1] == "engineer"


def test_a_plan_of_a_cell_that_serves_opc_ua_plays(example_cell: Path) -> None:
    """A plan serves no OPC UA: its copy of the cell leaves [opcua] (and its users file) out."""
    add_user(example_cell, "alice", "alice-pass")
    with (example_cell / "cell.toml").open("a", encoding="utf-8") as f:
        f.write('\n[opcua]\nlisten = "opc.tcp://127.0.0.1:4840"\nusers = "opcua-users.toml"\n')
    done = CliRunner().invoke(
        cli_main,
        ["plan", "--dir", str(example_cell), "--start", "08:00", "--shift", "1h",
         "--add", "wax-robot-base:1", "--json"],
    )  # fmt: skip
    assert done.exit_code == 0, done.output
    [order] = json.loads(done.output)["plans"][0]["orders"]
    assert order["order_id"] == "plan-add1" and order["made"] == 1


def test_wrong_logins_are_held_back_before_they_cost_the_server(example_cell: Path) -> None:
    """A name with LOGIN_FAILURES wrong passwords in the window from one address is refused
    unchecked from there (its right password too, until the window ends), and its later tries
    are not logged one by one; another name still logs in. Past LOGIN_FAILURES_ALL wrong
    logins of any names from one address, every login from it waits the window out; another
    address is not held back (tests/test_opcua_lockout.py: through real sockets)."""
    from cellctl.clock import run_virtual
    from cellctl.factory.opcua.users import (
        LOGIN_FAILURES,
        LOGIN_FAILURES_ALL,
        LOGIN_WINDOW_S,
        FileUserManager,
        login_from,
    )

    add_user(example_cell, "alice", "correct horse")
    add_user(example_cell, "bob", "battery staple")
    refused: list[tuple[str, str]] = []
    users = FileUserManager(
        example_cell / "opcua-users.toml",
        anonymous_read=False,
        refused=lambda name, peer: refused.append((name, peer)),
    )

    async def logins() -> None:
        from cellctl.clock import current_clock

        with login_from("10.0.0.5"):
            for _ in range(LOGIN_FAILURES):
                assert users.get_user(None, "alice", "guess") is None
            assert users.get_user(None, "alice", "correct horse") is None  # held back
            assert users.get_user(None, "alice", "guess") is None
            assert refused == [("alice", "10.0.0.5")] * LOGIN_FAILURES  # held-back tries unlogged
            assert users.get_user(None, "bob", "battery staple") is not None
        with login_from("10.0.0.7"):
            assert users.get_user(None, "alice", "correct horse") is not None  # elsewhere: in
        await current_clock().sleep(LOGIN_WINDOW_S)
        with login_from("10.0.0.5"):
            assert users.get_user(None, "alice", "correct horse") is not None
            for i in range(LOGIN_FAILURES_ALL):
                assert users.get_user(None, f"name{i % 20}", "guess") is None
            assert users.get_user(None, "bob", "battery staple") is None  # the address waits
        with login_from("10.0.0.7"):
            assert users.get_user(None, "bob", "battery staple") is not None
        await current_clock().sleep(LOGIN_WINDOW_S)
        with login_from("10.0.0.5"):
            assert users.get_user(None, "bob", "battery staple") is not None

    run_virtual(logins())
