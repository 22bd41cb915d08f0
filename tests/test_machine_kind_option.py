"""Which kind a `cellctl robot|mill` command drives: `--kind`, checked against cell.toml for a
NAME, and at `--link` the family's first kind unless only another has the command.

A UR named in a cell is driven by `cellctl robot --kind ur NAME status` through real TCP to
its emulator; a kind that contradicts cell.toml is refused before a byte goes out.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from cellctl.errors import UsageError
from cellctl.kinds import registry
from cellctl.kinds.ur.emulator import UrEmulator
from cellctl.service.machines import resolve_machine

from .conftest import CELLCTL

CELL = """\
[machines.arm]
kind = "ibm7545"
link = "socket://127.0.0.1:9"

[machines.cobot]
kind = "ur"
link = "{url}"
options = {{ secondary_port = {secondary}, rtde_port = {rtde} }}

[machines.cnc1]
kind = "dyna2400"
link = "socket://127.0.0.1:9"
"""


def write_cell(directory: Path, url: str = "socket://127.0.0.1:9", **ports: int) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    text = CELL.format(url=url, secondary=ports.get("secondary", 1), rtde=ports.get("rtde", 1))
    (directory / "cell.toml").write_text(text)
    return directory


def test_at_a_link_the_kind_is_given_or_the_one_that_has_the_command(tmp_path: Path) -> None:
    first = registry.names("robot")[0]
    at = "socket://127.0.0.1:29999"
    plain = resolve_machine(tmp_path, "robot", name=None, link=at, function="status")
    assert plain.kind == first  # both have status: the family's first
    unlock = resolve_machine(tmp_path, "robot", name=None, link=at, function="unlock")
    assert unlock.kind == "ur"  # only the UR has it
    given = resolve_machine(tmp_path, "robot", name=None, link=at, kind="ur", function="status")
    assert given.kind == "ur" and given.settings == registry.kind("ur").line_settings


def test_a_kind_of_another_family_or_none_installed_is_refused(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match=r"'dyna2400' is not a robot kind \(installed: .*ur"):
        resolve_machine(tmp_path, "robot", name=None, link="socket://h:1", kind="dyna2400")
    with pytest.raises(UsageError, match="'nope' is not a mill kind"):
        resolve_machine(tmp_path, "mill", name=None, link="socket://h:1", kind="nope")


def test_a_name_and_its_kind_are_checked_against_cell_toml(tmp_path: Path) -> None:
    cell = write_cell(tmp_path / "cell")
    with pytest.raises(UsageError, match="machine 'cobot' is a 'ur', not an 'ibm7545'"):
        resolve_machine(cell, "robot", name="cobot", link=None, kind="ibm7545")
    with pytest.raises(UsageError, match=r"which robot\? .*known: arm, cobot"):
        resolve_machine(cell, "robot", name=None, link=None)
    only = resolve_machine(cell, "robot", name=None, link=None, kind="ur")
    assert (only.name, only.kind) == ("cobot", "ur")  # the cell's only UR
    with pytest.raises(UsageError, match="unknown robot of kind ur 'arm2'"):
        resolve_machine(cell, "robot", name="arm2", link=None, kind="ur")


@pytest.fixture
async def cobot_cell(tmp_path: Path) -> AsyncIterator[Path]:
    emulator = UrEmulator(time_scale=100.0)
    ports = await emulator.start("127.0.0.1", dashboard=0, secondary=0, rtde_port=0)
    try:
        yield write_cell(
            tmp_path / "cell",
            emulator.dashboard_url,
            secondary=ports["secondary"],
            rtde=ports["rtde"],
        )
    finally:
        await emulator.close()


async def cellctl(cell: Path, *args: str) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, "--cell", str(cell), *args,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    async with asyncio.timeout(60):
        out, err = await proc.communicate()
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


async def test_robot_status_of_a_ur_by_name_prints_the_urs_words(cobot_cell: Path) -> None:
    code, out, err = await cellctl(cobot_cell, "robot", "--kind", "ur", "cobot", "status")
    assert code == 0, err
    assert "Robotmode: POWER_OFF" in out and "Safetystatus: NORMAL" in out
    code, out, err = await cellctl(cobot_cell, "robot", "cobot", "init")
    assert code == 0, err
    assert "Robotmode: RUNNING" in out


async def test_a_kind_that_contradicts_cell_toml_is_refused_before_a_byte(tmp_path: Path) -> None:
    accepted: list[bytes] = []

    async def count(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        accepted.append(await reader.read(100))
        writer.close()

    server = await asyncio.start_server(count, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    cell = write_cell(tmp_path / "cell", f"socket://127.0.0.1:{port}")
    try:
        code, out, err = await cellctl(cell, "robot", "--kind", "ibm7545", "cobot", "status")
    finally:
        server.close()
        await server.wait_closed()
    assert code == 2 and out == ""
    assert "machine 'cobot' is a 'ur', not an 'ibm7545'" in err
    assert accepted == []  # the link was never opened
