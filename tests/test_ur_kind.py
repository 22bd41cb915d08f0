"""The UR kind as a plug-in: the registry, its docs, `cellctl emulate ur` as a process, and
what any peer may send its emulator (property tests: typed answers, nothing hangs)."""

from __future__ import annotations

import asyncio
import re
import subprocess
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cellctl.kinds import registry
from cellctl.kinds.families import Robot
from cellctl.kinds.ur.dashboard import BANNER, COMMANDS, NOT_UNDERSTOOD, RobotMode
from cellctl.kinds.ur.driver import UrOptions, UrRobot
from cellctl.kinds.ur.emulator import UrController, UrEmulator

from .conftest import CELLCTL

ROOT = Path(__file__).resolve().parent.parent


def test_listed_documented_and_named_only_in_its_package() -> None:
    out = subprocess.run(
        [*CELLCTL, "kinds"], capture_output=True, text=True, timeout=60, check=True
    ).stdout
    line = next(row for row in out.splitlines() if row.startswith("ur "))
    assert "robot" in line and "Universal Robots" in line and "cellctl" in line
    docs = (ROOT / "docs" / "kinds.md").read_text(encoding="utf-8")
    assert registry.kind("ur").options_table() in docs
    assert "## A cobot tending your CNC" in (ROOT / "README.md").read_text(encoding="utf-8")
    naming = subprocess.run(
        ["git", "grep", "-l", "-E", r"kinds\.ur\b|\"ur\"", "--", "src"],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    ).stdout.split()  # fmt: skip
    # The example cells are data: their cell.toml names the kinds of their machines.
    outside = ("src/cellctl/kinds/ur/", "src/cellctl/examples/")
    assert [p for p in naming if not p.startswith(outside)] == []
    own = ("name", "link", "initialized")
    missing = [
        m for m in dir(Robot) if not m.startswith("_") and not hasattr(UrRobot, m) and m not in own
    ]
    assert missing == []


def test_a_bad_option_is_refused_by_its_name() -> None:
    kind = registry.kind("ur")
    try:
        kind.checked_options({"model": "UR99"})
    except Exception as e:
        assert "model" in str(e)
    else:
        raise AssertionError("an unknown model was accepted")


async def test_cellctl_emulate_ur_serves_the_driver() -> None:
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, "emulate", "ur", "--dashboard-port", "0", "--secondary-port", "0",
        "--rtde-port", "0", "--time-scale", "50", "--fault", "local_mode",
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        said = ""
        while "link = " not in said:
            async with asyncio.timeout(30):
                row = await proc.stdout.readline()
            assert row, f"the emulator ended saying {said!r}"
            said += row.decode()
        ports = dict(re.findall(r"(secondary|RTDE) (\d+)", said))
        # At ports of its own it says what a cell.toml needs to reach it: those ports.
        url = re.findall(r'link = "([^"]+)"', said)[0]
        said_options = dict(re.findall(r"(secondary_port|rtde_port) = (\d+)", said))
        assert said_options == {"secondary_port": ports["secondary"], "rtde_port": ports["RTDE"]}
        options = UrOptions(secondary_port=int(ports["secondary"]), rtde_port=int(ports["RTDE"]))
        robot = await UrRobot.connect(url, name="ur-cli", options=options)
        try:
            assert await robot.remote_control() is False  # --fault local_mode
            assert (await robot.machine_status()).mode == RobotMode.POWER_OFF
        finally:
            await robot.close()
    finally:
        proc.terminate()
        async with asyncio.timeout(10):
            await proc.wait()


@given(st.text(max_size=120))
def test_the_dashboard_answers_any_line_in_one_line(line: str) -> None:
    async def answered() -> str:
        # In a running loop, as the emulator answers: a command whose effect comes later
        # ("power on") schedules it there (a loop of its own per line: no test's loop
        # left behind, or missing, decides the outcome).
        return UrController(time_scale=1000.0).answer(line)

    answer = asyncio.run(answered())
    assert len(answer.splitlines()) == 1
    command = next((c for c in COMMANDS.values() if line.strip().startswith(c.text)), None)
    if command is None:
        assert answer.startswith(NOT_UNDERSTOOD.split("{")[0])


_lines = st.lists(
    st.one_of(
        st.sampled_from(["def a():", "end", "while True:", "sleep(0.01)", "movej([0,0,0,0,0,0])"]),
        st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=40),
    ),
    max_size=12,
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_lines, st.binary(max_size=64))
async def test_any_bytes_on_the_three_ports_leave_it_serving(
    script: list[str], rtde_bytes: bytes
) -> None:
    emu = UrEmulator(time_scale=1000.0)
    await emu.start("127.0.0.1")
    emu.controller.mode = RobotMode.RUNNING
    try:
        for port, data in (
            ("secondary", ("\n".join(script) + "\n").encode("utf-8", "replace")),
            ("rtde", rtde_bytes),
            ("dashboard", b"\n".join(s.encode("utf-8", "replace") for s in script) + b"\n"),
        ):
            _, writer = await asyncio.open_connection("127.0.0.1", emu.ports[port])
            writer.write(data)
            await writer.drain()
            writer.close()
        # Still serving: a new client gets the banner and an answer.
        reader, writer = await asyncio.open_connection("127.0.0.1", emu.ports["dashboard"])
        async with asyncio.timeout(5):
            assert (await reader.readline()).decode().strip() == BANNER
        writer.write(b"robotmode\n")
        async with asyncio.timeout(5):
            assert (await reader.readline()).startswith(b"Robotmode: ")
        writer.close()
    finally:
        await emu.close()
