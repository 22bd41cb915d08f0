"""A machine kind from outside cellctl: the Kerf 100 bar saw of tests/plugins/cellctl_saw,
installed into the test environment as a user installs a plug-in (``make deps``).

Everything here goes through cellctl's registry and real links: ``cellctl kinds`` lists it,
``cell check`` checks its options, its driver talks to its emulator over a pty, and
``cellctl emulate cell`` + ``cellctl run`` cut a batch through a Dyna 2400 and the saw while
the control API and OPC UA show the saw with its condition."""

from __future__ import annotations

import asyncio
import shutil
import signal
import socket
import subprocess
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
from asyncua import ua
from hypothesis import given
from hypothesis import strategies as st

from cellctl.cell.journal import open_journal
from cellctl.emulators.serve import serve
from cellctl.errors import AccessDenied, CellctlError, DeviceError, ProtocolError, UsageError
from cellctl.factory.opcua import NAMESPACE
from cellctl.factory.opcua.figures import MACHINE_CONDITIONS
from cellctl.kinds import Condition, registry
from cellctl.kinds.families import Mill
from cellctl.kinds.kind import DriverSpec, EmulatorSpec
from cellctl.link import TrafficLog
from cellctl.mailbox import open_mailbox
from cellctl.service.client import RemoteCell, attach
from cellctl.service.token import read_token

from .conftest import CELLCTL, wait_until
from .test_opcua import client_cert, session  # noqa: F401 - client_cert is a fixture

ROOT = Path(__file__).resolve().parent.parent
TEMPLATE = ROOT / "tests" / "plugins" / "kerf_cell"
KIND = "kerf100"
TIME_SCALE = "400"


def saw_kind():  # type: ignore[no-untyped-def]
    return registry.kind(KIND)


def cellctl(cell: Path, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "--cell", str(cell), *args], capture_output=True, text=True, timeout=timeout
    )


def said(result: subprocess.CompletedProcess[str]) -> str:
    """What a command printed, its lines joined (the terminal wraps long paths)."""
    return (result.stdout + result.stderr).replace("\n", "")


def template_copy(directory: Path) -> Path:
    """The mill-and-saw template copied as it stands (``cp -r tests/plugins/kerf_cell DIR``),
    nothing added: what docs/kinds.md step 7 starts from."""
    shutil.copytree(TEMPLATE, directory)
    return directory


def named_files(template: Path) -> set[Path]:
    """Every file the template's cell.toml names: setups, robot programs, route programs."""
    raw = tomllib.loads((template / "cell.toml").read_text(encoding="utf-8"))
    names = {m["setup"] for m in raw["machines"].values() if "setup" in m}
    names |= set(raw["robot_programs"].values())
    names |= {step["program"] for part in raw["parts"].values() for step in part["route"]}
    return {template / name for name in names}


# -- the registry and the command line -----------------------------------------------------------


def test_cellctl_kinds_lists_the_saw_with_where_it_comes_from() -> None:
    out = cellctl(Path("."), "kinds").stdout
    row = next(line for line in out.splitlines() if line.startswith(KIND))
    assert "mill" in row and "Kerf" in row and "cellctl-saw" in row
    assert saw_kind().origin is not None and saw_kind().origin.module == "cellctl_saw.kind"
    assert registry.broken() == {}


def test_the_template_holds_every_file_its_cell_toml_names() -> None:
    # The template itself, where it stands: `cell check` reads every file it names.
    named = named_files(TEMPLATE)
    assert len(named) == 7 and all(path.is_file() for path in named), sorted(map(str, named))
    checked = cellctl(TEMPLATE, "cell", "check")
    assert checked.returncode == 0, said(checked)
    assert "ok: robot robot, mills cnc1, saw, 3 robot programs, part types bar-end" in said(checked)


def test_cell_check_validates_the_saw_s_options(tmp_path: Path) -> None:
    cell = template_copy(tmp_path / "cell")
    good = cellctl(cell, "cell", "check")
    assert good.returncode == 0, good.stdout + good.stderr
    toml = cell / "cell.toml"
    text = toml.read_text()
    toml.write_text(
        text.replace(
            'setup = "programs/saw_setup.cut"',
            'setup = "programs/saw_setup.cut"\noptions = { reply_timeout = -1 }',
        )
    )
    bad = cellctl(cell, "cell", "check")
    assert bad.returncode != 0
    assert "machines.saw" in said(bad) and "reply_timeout" in said(bad)
    toml.write_text(
        text.replace(
            'setup = "programs/saw_setup.cut"',
            'setup = "programs/saw_setup.cut"\noptions = { blade_rpm = 3000 }',
        )
    )
    unknown = cellctl(cell, "cell", "check")
    assert unknown.returncode != 0 and "blade_rpm" in said(unknown)
    # The saw's program language checks its cut lists with the rest of the cell.
    toml.write_text(text)
    (cell / "programs" / "bars.cut").write_text("CUT 120 300\nCUT 9000 300\n")
    too_long = cellctl(cell, "cell", "check")
    assert too_long.returncode != 0 and "bars.cut:2: length" in said(too_long)


# -- the driver against its emulator, over a pty ------------------------------------------------


async def test_cellctl_mill_drives_a_saw_at_a_link_given_its_kind(tmp_path: Path) -> None:
    kind = saw_kind()
    emulator = kind.emulator(EmulatorSpec(time_scale=200.0))
    server = await serve(emulator, "pty", kind.line_settings)
    try:
        proc = await asyncio.create_subprocess_exec(
            *CELLCTL, "--cell", str(tmp_path / "none"), "mill", "--kind", "kerf100",
            "--link", server.url, "status",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        async with asyncio.timeout(60):
            out, err = await proc.communicate()
    finally:
        await server.close()
    # The saw's own status in its words, read at its own line settings (9600,8N1).
    assert proc.returncode == 0, err.decode()
    assert out.decode().strip() == "not homed"


async def test_the_driver_cuts_homes_and_reports_the_emulator_s_faults(tmp_path: Path) -> None:
    kind = saw_kind()
    emulator = kind.emulator(EmulatorSpec(time_scale=200.0))
    server = await serve(emulator, "pty", kind.line_settings)
    options = kind.checked_options({"reply_timeout": 1.0})
    trace = TrafficLog(None, keep=1000)
    saw = await kind.open(DriverSpec(server.url, "saw", kind.line_settings, options, trace=trace))
    try:
        assert isinstance(saw, Mill)
        (tmp_path / "setup.cut").write_text("HOME\n")
        (tmp_path / "bars.cut").write_text("CUT 100 600\nCUT 50 600\n")
        status = await saw.status()
        assert status.kind_condition is Condition.NOT_READY and not status.takes_work
        with pytest.raises(DeviceError, match="NOT HOMED"):
            await saw.ask("RUN")
        await saw.setup(tmp_path / "setup.cut", force=True)
        assert (await saw.status()).kind_condition is Condition.IDLE
        phases: list[str] = []
        await saw.run(tmp_path / "bars.cut", progress=lambda p: phases.append(p.phase))
        status = await saw.status()
        assert status.done == 2 and status.loaded == 2 and phases[-1] == "done"
        assert len(emulator.runs) == 1 and emulator.runs[0].cuts == 2
        # A bad cut list is refused before a byte goes out.
        (tmp_path / "bad.cut").write_text("CUT -3 600\n")
        sent = trace.sent()
        with pytest.raises(UsageError, match=r"bad\.cut:1: length"):
            await saw.run(tmp_path / "bad.cut")
        assert trace.sent() == sent and sent.endswith(b"ST\r\n")
        # A jam: the run fails with the saw's alarm, the condition says so.
        emulator.set_fault("jam")
        with pytest.raises(DeviceError, match="blade jammed"):
            await saw.run(tmp_path / "bars.cut")
        assert (await saw.status()).kind_condition is Condition.ALARM
        emulator.clear_fault("jam")
        emulator.set_fault("no-home")
        with pytest.raises(DeviceError, match="HOME SWITCH"):
            await saw.setup(tmp_path / "setup.cut", force=True)
        emulator.clear_fault("no-home")
        await saw.setup(tmp_path / "setup.cut", force=True)
        assert (await saw.status()).kind_condition is Condition.IDLE
    finally:
        await saw.close()
        await server.close()


@given(st.binary(max_size=60))
def test_whatever_the_saw_answers_is_a_reply_or_a_typed_error(raw: bytes) -> None:
    from cellctl_saw.protocol import parse_reply, parse_status

    for parse in (parse_reply, parse_status):
        try:
            parse(raw)
        except (DeviceError, ProtocolError) as e:
            assert str(e)


@given(st.text(max_size=200))
def test_any_cut_list_text_parses_with_its_problems_named(text: str) -> None:
    from cellctl_saw.protocol import parse_cut_list

    found = parse_cut_list(text, "x.cut", setup=False)
    assert all(p.startswith("x.cut") for p in found.problems)
    assert found.problems or found.cuts


# -- the whole cell: a Dyna 2400 and the saw ----------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def mill_and_saw(tmp_path: Path) -> Iterator[Path]:
    """``cellctl emulate cell --template`` the mill-and-saw cell, and ``cellctl run`` on it,
    each in its own process; yields the cell directory once the API listens."""
    # As docs/kinds.md step 7: the template copied as it stands, emulated, then run.
    template = template_copy(tmp_path / "kc")
    cell = tmp_path / "cell"
    emulate = subprocess.Popen(
        [
            *CELLCTL,
            "--cell",
            str(cell),
            "emulate",
            "cell",
            "--time-scale",
            TIME_SCALE,
            "--template",
            str(template),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    run: subprocess.Popen[str] | None = None
    try:
        assert emulate.stdout is not None
        for line in emulate.stdout:
            if line.strip().startswith("plc"):
                break
        # The emulated cell as written is a good one: every file its template named came along.
        checked = cellctl(cell, "cell", "check")
        assert checked.returncode == 0, said(checked)
        # Then this test's own settings: a faster poll, and OPC UA on a free port.
        toml = cell / "cell.toml"
        toml.write_text(
            toml.read_text().replace("poll_period = 0.5", "poll_period = 0.1")
            + f'\n[opcua]\nlisten = "opc.tcp://127.0.0.1:{free_port()}"\nanonymous_read = true\n'
        )
        with open_mailbox(cell) as mailbox:
            mailbox.post_order("bar-end", 2, order_id="A")
        log = (tmp_path / "run.log").open("w")
        run = subprocess.Popen(
            [*CELLCTL, "--cell", str(cell), "run", "--no-live"],
            stdout=log,
            stderr=subprocess.STDOUT,
            text=True,
        )
        wait_until(lambda: (cell / "api.sock").exists(), "the API socket")
        yield cell
    finally:
        if run is not None and run.poll() is None:
            run.send_signal(signal.SIGINT)
            try:
                run.wait(60)
            except subprocess.TimeoutExpired:
                run.kill()
        emulate.terminate()
        emulate.wait(10)


async def test_a_batch_runs_through_the_mill_and_the_saw(
    mill_and_saw: Path,
    client_cert: tuple[str, str],  # noqa: F811 - the fixture
) -> None:
    cell = mill_and_saw
    async with await attach(cell) as api:

        async def order_done() -> bool:
            orders = await api.call("orders.list", {})
            return any(o["id"] == "A" and o["state"] == "done" for o in orders)

        deadline = time.monotonic() + 60
        while not await order_done():
            assert time.monotonic() < deadline, "order A was not done in time"
            await asyncio.sleep(0.1)
        # Both parts went through both machines: two cuts on each.
        with open_journal(cell) as journal:
            steps = journal.steps()
        done = [s for s in steps if s.kind == "machine" and s.state == "finished"]
        assert sorted((s.machine, s.program) for s in done) == [
            ("cnc1", "robot_base_rough_cnc1"),
            ("cnc1", "robot_base_rough_cnc1"),
            ("saw", "bars"),
            ("saw", "bars"),
        ], steps

        # The status model shows the saw with its kind and condition.
        status = await api.call("cell.status", {})
        saw = status["machines"]["saw"]
        assert saw["kind"] == KIND and saw["condition"] in {c.value for c in Condition}

        # Its own menu, by its machine name; the mill's kind has no such function.
        answer = await api.call("mill.status", {"machine": "saw"})
        assert answer["machine"] == "saw" and answer["message"].startswith("idle")
        with pytest.raises(UsageError, match="on a dyna2400"):
            await api.call("mill.home", {"machine": "cnc1"})
        with pytest.raises(CellctlError, match="automatic service"):
            await api.call("mill.home", {"machine": "saw"})  # it acts: out of service only
    with pytest.raises(AccessDenied):
        await RemoteCell.connect(token=read_token(cell) + "x", socket_path=cell / "api.sock")

    # OPC UA shows the saw from the same status, with no code of its own.
    url = (cell / "cell.toml").read_text().split('listen = "', 1)[1].split('"', 1)[0]
    async with session(url, cell, client_cert) as client:
        idx = await client.get_namespace_index(NAMESPACE)
        node = client.get_node(ua.NodeId("Machines/saw/Monitoring/Condition", idx))
        value = await node.read_value()
        assert MACHINE_CONDITIONS[int(value)] in ("Idle", "Busy", "NotReady")
        maker = client.get_node(ua.NodeId("Machines/saw/Identification/Manufacturer", idx))
        assert "Kerf" in str(await maker.read_value())
