"""A UR whose RTDE and secondary interface are not at 30004 and 30002: driven by ``--link``
(the ports on the link URL) as `cellctl emulate ur` says, and a port that does not answer
named by its interface. The driver and the CLI against the UR emulator over real sockets."""

from __future__ import annotations

import asyncio
import re
import shlex
import subprocess
from collections.abc import AsyncIterator
from urllib.parse import urlsplit

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cellctl.errors import LinkError, UsageError
from cellctl.kinds.ur.dashboard import RuntimeState
from cellctl.kinds.ur.driver import UrOptions, UrRobot
from cellctl.kinds.ur.emulator import UrEmulator
from cellctl.kinds.ur.options import link_ports
from cellctl.kinds.ur.program import compile_program
from tests.conftest import CELLCTL, refusing_port

SCRIPT = "def lit():\n  set_standard_digital_out(3, True)\nend\n"

#: Options that leave the ports to the link URL (deadlines short for the emulator).
QUICK = UrOptions(power_on_timeout=10, brake_release_timeout=10)


@pytest.fixture
async def emulator() -> AsyncIterator[UrEmulator]:
    emu = UrEmulator(time_scale=20.0)
    await emu.start("127.0.0.1")  # free ports: none of them the defaults
    yield emu
    await emu.close()


def ports_url(emu: UrEmulator, **ports: int) -> str:
    query = "&".join(f"{key}={port}" for key, port in ports.items())
    return f"{emu.dashboard_url}?{query}"


async def test_the_link_url_gives_both_ports(emulator: UrEmulator) -> None:
    url = ports_url(
        emulator, rtde_port=emulator.ports["rtde"], secondary_port=emulator.ports["secondary"]
    )
    robot = await UrRobot.connect(url, name="ur-ports", options=QUICK)
    try:
        assert robot.options.rtde_port == emulator.ports["rtde"]  # RTDE streams: it connected
        await robot.initialize()
        slot = await robot.ensure_program("lit", compile_program(SCRIPT, "lit", "lit.script"))
        await robot.start(slot)  # the script goes out on the secondary port the URL named
        await robot.wait_end(0, timeout=30)
        assert (await robot.machine_status()).output(3)
    finally:
        await robot.close()


async def test_an_interface_that_does_not_answer_is_named_with_its_port(
    emulator: UrEmulator,
) -> None:
    with refusing_port() as held:
        dead = held.getsockname()[1]
        with pytest.raises(LinkError) as rtde:
            await UrRobot.connect(ports_url(emulator, rtde_port=dead), name="ur-x", options=QUICK)
        said = str(rtde.value)
        assert f"the UR's RTDE at port {dead} cannot be reached" in said
        assert f"--link '{emulator.dashboard_url}?rtde_port=PORT'" in said
        assert "rtde_port = PORT" in said  # and the cell.toml's way

        url = ports_url(emulator, rtde_port=emulator.ports["rtde"], secondary_port=dead)
        robot = await UrRobot.connect(url, name="ur-y", options=QUICK)
        try:
            await robot.initialize()
            slot = await robot.ensure_program("lit", compile_program(SCRIPT, "lit", "l.script"))
            with pytest.raises(LinkError, match=f"secondary interface at port {dead} cannot be"):
                await robot.start(slot)
            assert emulator.controller.runtime == RuntimeState.STOPPED  # nothing ran
        finally:
            await robot.close()


@pytest.mark.parametrize(
    ("query", "said"),
    [
        ("rtde=30004", "'rtde' is not a UR link setting"),
        ("rtde_port=0", "rtde_port is a port 1-65535, not '0'"),
        ("rtde_port=70000", "rtde_port is a port 1-65535, not '70000'"),
        ("secondary_port=x", "secondary_port is a port 1-65535, not 'x'"),
        ("rtde_port=1&rtde_port=2", "rtde_port given twice"),
    ],
)
async def test_a_bad_port_on_the_link_is_refused_before_it_opens(query: str, said: str) -> None:
    with refusing_port() as held:  # a connection there would fail as LinkError, not this
        url = f"socket://127.0.0.1:{held.getsockname()[1]}?{query}"
        with pytest.raises(UsageError, match=re.escape(said)):
            await UrRobot.connect(url, options=QUICK)


async def test_a_port_in_the_url_and_another_in_the_options_is_refused() -> None:
    with refusing_port() as held:
        url = f"socket://127.0.0.1:{held.getsockname()[1]}?rtde_port=30014"
        with pytest.raises(UsageError, match="rtde_port 30014 in the link URL, 30004 in the"):
            await UrRobot.connect(url, options=UrOptions(rtde_port=30004))
    with pytest.raises(UsageError, match="mem:// UR takes no ports"):
        await UrRobot.connect("mem://ur?rtde_port=30014")


@given(st.text(max_size=60))
def test_any_query_is_ports_or_a_usage_error(query: str) -> None:
    try:
        dashboard, ports = link_ports(f"socket://127.0.0.1:29999?{query}")
    except UsageError:
        return
    parts = urlsplit(dashboard)
    assert (parts.hostname, parts.port, parts.query) == ("127.0.0.1", 29999, "")
    assert set(ports) <= {"rtde_port", "secondary_port"}
    assert all(1 <= p <= 65535 for p in ports.values())


async def _said_until(proc: asyncio.subprocess.Process, marker: str) -> str:
    assert proc.stdout is not None
    said = ""
    while marker not in said:
        async with asyncio.timeout(30):
            row = await proc.stdout.readline()
        assert row, f"the emulator ended saying {said!r}"
        said += row.decode()
    return said


async def _cellctl(*args: str) -> subprocess.CompletedProcess[str]:
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, *args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    async with asyncio.timeout(60):
        out, err = await proc.communicate()
    assert proc.returncode is not None
    return subprocess.CompletedProcess(args, proc.returncode, out.decode(), err.decode())


async def test_cellctl_emulate_ur_at_its_own_ports_says_a_command_that_works() -> None:
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, "emulate", "ur", "--dashboard-port", "0", "--secondary-port", "0",
        "--rtde-port", "0", "--time-scale", "50",
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    try:
        said = await _said_until(proc, "drive it with: ")
        ports = dict(re.findall(r"(dashboard|secondary|RTDE) (\d+)", said))
        hint = said.split("drive it with: ", 1)[1].splitlines()[0]
        words = shlex.split(hint)  # as a shell reads it
        assert words[0] == "cellctl"
        done = await _cellctl(*words[1:], "status")
        assert done.returncode == 0, done.stderr
        assert "Robotmode: POWER_OFF" in done.stdout

        # A port that does not answer: the error says which interface, at which port, and
        # how to give another.
        with refusing_port() as held:
            dead = held.getsockname()[1]
            plain = f"socket://127.0.0.1:{ports['dashboard']}"
            link = f"{plain}?rtde_port={dead}"
            done = await _cellctl("robot", "--kind", "ur", "--link", link, "status")
        assert done.returncode == 3
        assert f"the UR's RTDE at port {dead} cannot be reached" in done.stderr
        assert f"--link '{plain}?rtde_port=PORT'" in done.stderr
    finally:
        proc.terminate()
        async with asyncio.timeout(10):
            await proc.wait()


def test_at_the_default_ports_the_hint_is_the_plain_link() -> None:
    from cellctl.kinds.ur.options import drive_command

    plain = "cellctl robot --kind ur --link socket://10.0.0.5:29999"
    assert drive_command("socket://10.0.0.5:29999", 30002, 30004) == plain
    assert drive_command("socket://10.0.0.5:29999", 30002, 30014) == (
        "cellctl robot --kind ur --link 'socket://10.0.0.5:29999?rtde_port=30014'"
    )


async def test_the_dashboard_link_is_opened_without_the_ports(emulator: UrEmulator) -> None:
    url = ports_url(
        emulator, secondary_port=emulator.ports["secondary"], rtde_port=emulator.ports["rtde"]
    )
    robot = await UrRobot.connect(url, name="ur-z", options=QUICK)
    try:
        assert robot.link.url == emulator.dashboard_url
        assert robot.options.secondary_port == emulator.ports["secondary"]
    finally:
        await robot.close()
