"""What `cellctl program check` says of a UR script: one the driver cannot run (empty, no
``def``) is a problem in words, and a pose out of reach names the model checked, with its
reach. The driver refuses the same scripts before a byte goes out."""

from __future__ import annotations

import subprocess
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from cellctl.errors import UsageError
from cellctl.kinds import registry
from cellctl.kinds.kind import ProgramRole
from cellctl.kinds.ur.driver import UrOptions, UrRobot
from cellctl.kinds.ur.emulator import UrEmulator
from cellctl.kinds.ur.program import UrProgram, compile_program
from tests.conftest import CELLCTL

FAR = "def far():\n  movel(p[5, 0, 0.2, 0, 0, 0])\nend\n"  # 5 m: no UR reaches it
FORM = "a UR script is one 'def {}(): ... end' holding the program's statements"


def _check(*files: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "program", "check", "--kind", "ur", *map(str, files)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip


def test_a_script_the_driver_cannot_run_is_a_problem(tmp_path: Path) -> None:
    empty = tmp_path / "empty.script"
    empty.write_text("")
    notes = tmp_path / "notes.script"
    notes.write_text("# to do: the moves\n\n")
    bare = tmp_path / "bare.script"
    bare.write_text("# a move\nmovej([0, -1.57, 0, -1.57, 0, 0])\n")
    for file in (empty, notes, bare):
        done = _check(file)
        assert done.returncode == 1, done.stdout
        assert "a good ur program" not in done.stdout
        assert FORM.format(file.stem) in done.stdout
    assert f"{empty}: empty: " in _check(empty).stdout
    assert f"{bare}:2:1: not inside a 'def': " in _check(bare).stdout


def test_a_pose_out_of_reach_names_the_model_checked(tmp_path: Path) -> None:
    far = tmp_path / "far.script"
    far.write_text(FAR)
    done = _check(far)
    assert done.returncode == 1
    # The documented default model, UR5e, with its own reach (not the longest arm's).
    assert "pose out of reach for a UR5e: 5.004 m from the base, its reach is 0.850 m" in (
        done.stdout
    )
    assert "UR10e" not in done.stdout

    language = registry.kind("ur").language
    assert language is not None
    on_ur10e = language.check(far, ProgramRole.TRANSFER, UrOptions(model="UR10e"))
    assert any("for a UR10e: 5.004 m from the base, its reach is 1.300 m" in p
               for p in on_ur10e.problems)  # fmt: skip


def test_before_the_model_is_known_the_check_says_any_model() -> None:
    # A cell's [robot_programs] are compiled before the robot's model is read: no UR.
    with pytest.raises(UsageError, match=r"for a UR of any model \(the longest reach is a UR10e"):
        compile_program(FAR, "far", "robot/far.script")
    with pytest.raises(UsageError, match="empty: a UR script is one 'def e"):
        compile_program("\n", "e", "robot/e.script")


@pytest.fixture
async def robot() -> AsyncIterator[UrRobot]:
    emu = UrEmulator(time_scale=20.0)
    await emu.start("127.0.0.1")
    options = UrOptions(secondary_port=emu.ports["secondary"], rtde_port=emu.ports["rtde"])
    r = await UrRobot.connect(emu.dashboard_url, name="ur-check", options=options)
    yield r
    await r.close()
    await emu.close()


async def test_the_driver_refuses_a_script_without_a_def(robot: UrRobot) -> None:
    bare = UrProgram("bare", "bare.script", text="movej([0, -1.57, 0, -1.57, 0, 0])\n")
    with pytest.raises(UsageError, match=r"bare\.script:1:1: not inside a 'def'"):
        await robot.ensure_program("bare", bare)
