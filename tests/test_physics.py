"""The physical bound's inputs, against figures worked out by hand from the machines' tables.

A tiny cell: one part type through CNC 1 and CNC 2, each cutting a 1-inch feed move, and three
robot programs whose motion, door and vise waits are easy to add up. Every expected figure
below is written out from the emulators' constants (arm speed, gripper time, PLC door and vise
times) and the line's format, never read back from the module under test.
"""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import pytest

from cellctl.cell.config import load_cell
from cellctl.cell.physics import physical_durations
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.emulators.serve import serve
from cellctl.factory.bound import physical_bound, split_bound
from cellctl.kinds.dyna2400.driver import Dyna2400Mill
from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator, OperatorDelays
from cellctl.kinds.ibm7545.aml import OPCODES, compile_program
from cellctl.kinds.ibm7545.motion import GRIPPER_S, SPEED_MM_S, timeline
from cellctl.link import LineSettings
from cellctl.protocol.plc import PlcTiming

TIMING = PlcTiming()
BITS_PER_CHAR = 1 + 7 + 1 + 2  # 4800,7E2: start, 7 data, even parity, 2 stop
BAUD = 4800

# From home (650, 0) or from the safe point (400, 0) where the others leave the arm: the
# least is 300 mm from the safe point. Then the door of CNC 1 (commanded as the transfer
# starts), the gripper, the vise the program closes, and 300 mm back.
LOAD = """
        PMOVE(PT(400, 300, 0, 0))
        WAITI(2, 1)
        GRASP
        WRITEO(1, 1)
        WAITI(4, 1)
        PMOVE(PT(400, 0, 0, 0))
        WRITEO(6, 1)
        END
"""
LOAD_S = max(300 / SPEED_MM_S, TIMING.door_s) + GRIPPER_S + TIMING.clamp_s + 300 / SPEED_MM_S
# CNC 2's door, then a DELAY of 1.0 s; the door of CNC 1 opens too, but nothing waits for it.
ADVANCE = """
        WAITI(5, 1)
        DELAY(1.0)
        WRITEO(6, 1)
        END
"""
ADVANCE_S = TIMING.door_s + 1.0
# Down and up: no door on the conveyor's side is waited for.
UNLOAD = """
        PMOVE(PT(400, 0, 0, 0))
        DOWN
        UP
        WRITEO(6, 1)
        END
"""
UNLOAD_S = 2 * GRIPPER_S

# One inch along X at 10 inches a minute: 6 s of cutting.
MILL_LINES = ["000 FR X = 10.0", "001 GR X 1.000", "002 SKIP TO 900", "900"]
CUT_S = 1.0 / 10.0 * 60.0
MILL_CHARS = sum(len(line) + 2 for line in MILL_LINES) + 1  # CR LF each, then Ctrl-Z


def robot_download_chars(source: str) -> int:
    """Characters of one download, from the record format: ident, 2 hex digits of length,
    the data in hex, 2 of checksum, CR LF; the controller's Ack after the identifier and
    after each record."""
    body = [1 + struct.calcsize(OPCODES[ins.op].fmt) for ins in compile_program(source)]
    records = [1 + 8, *body, 0]  # N: partition and 8-character name; D...; E (end)
    return sum(1 + 2 + 2 * n + 2 + 2 for n in records) + len(records) + 1


@pytest.fixture
def tiny_cell(tmp_path: Path) -> Path:
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    for name, text in (
        ("conveyor_to_cnc1", LOAD),
        ("cnc1_to_cnc2", ADVANCE),
        ("cnc2_to_conveyor", UNLOAD),
    ):
        (cell / "robot" / f"{name}.aml").write_text(text, encoding="ascii")
    for name in ("tiny_a", "tiny_b"):
        (cell / "programs" / f"{name}.dyn").write_text("\n".join(MILL_LINES) + "\n")
    toml = (cell / "cell.toml").read_text(encoding="utf-8")
    toml = toml[: toml.index("[parts.wax-robot-base]")] + (
        '[parts.tiny]\nroute = [\n  { mill = "cnc1", program = "programs/tiny_a.dyn" },\n'
        '  { mill = "cnc2", program = "programs/tiny_b.dyn" },\n]\n'
    )
    (cell / "cell.toml").write_text(toml, encoding="utf-8")
    return cell


def test_a_robot_program_takes_its_moves_gripper_and_delays() -> None:
    # From home (650, 0): 250 mm to the safe point, the gripper, half a second.
    source = "PMOVE(PT(400, 0, 0, 0))\nGRASP\nDELAY(0.5)\nWRITEO(6, 1)\nEND\n"
    run = timeline(compile_program(source))
    assert run.first_write(6, True) == pytest.approx(250 / SPEED_MM_S + GRIPPER_S + 0.5)
    assert run.position == (400.0, 0.0, 0.0, 0.0)


def test_each_step_takes_what_the_machines_physically_do(tiny_cell: Path) -> None:
    phys = physical_durations(load_cell(tiny_cell))
    assert phys.transfers["conveyor_to_cnc1"].seconds == pytest.approx(LOAD_S)
    assert phys.transfers["conveyor_to_cnc1"].parts["clamp"] == pytest.approx(TIMING.clamp_s)
    assert phys.transfers["cnc1_to_cnc2"].seconds == pytest.approx(ADVANCE_S)
    assert phys.transfers["cnc2_to_conveyor"].seconds == pytest.approx(UNLOAD_S)
    wire = MILL_CHARS * BITS_PER_CHAR / BAUD
    for mill, program in (("cnc1", "tiny_a"), ("cnc2", "tiny_b")):
        step = phys.machining[(mill, program)]
        assert step.parts == pytest.approx({"door": TIMING.door_s, "download": wire, "cut": CUT_S})
        assert step.seconds == pytest.approx(TIMING.door_s + wire + CUT_S)
    for name, source in (
        ("conveyor_to_cnc1", LOAD),
        ("cnc1_to_cnc2", ADVANCE),
        ("cnc2_to_conveyor", UNLOAD),
    ):
        expected = robot_download_chars(source) * BITS_PER_CHAR / BAUD
        assert phys.robot_downloads[name] == pytest.approx(expected)


def test_the_time_scale_divides_every_machine_time(tiny_cell: Path) -> None:
    config = load_cell(tiny_cell)
    real = physical_durations(config)
    fast = physical_durations(config, time_scale=50.0)
    # The line's rate is the configuration's (an emulated cell writes it scaled already).
    wire = MILL_CHARS * BITS_PER_CHAR / BAUD
    assert fast.machining[("cnc1", "tiny_a")].seconds == pytest.approx(
        (TIMING.door_s + CUT_S) / 50 + wire
    )
    assert fast.transfers["cnc1_to_cnc2"].seconds == pytest.approx(
        real.transfers["cnc1_to_cnc2"].seconds / 50
    )


def test_the_bound_of_a_batch_from_physics(tiny_cell: Path) -> None:
    config = load_cell(tiny_cell)
    phys = physical_durations(config)
    downloads = sum(robot_download_chars(s) for s in (LOAD, ADVANCE, UNLOAD))
    dl = downloads * BITS_PER_CHAR / BAUD
    cut = TIMING.door_s + MILL_CHARS * BITS_PER_CHAR / BAUD + CUT_S
    # Three parts. The robot: its downloads once, then every transfer.
    robot = dl + 3 * (LOAD_S + ADVANCE_S + UNLOAD_S)
    # CNC 1: nothing before it; load, cut, advance per part; after it, CNC 2's cut and unload.
    cnc1 = 3 * (LOAD_S + cut + ADVANCE_S) + cut + UNLOAD_S
    # CNC 2: a load and CNC 1's cut before it; advance, cut, unload per part.
    cnc2 = LOAD_S + cut + 3 * (ADVANCE_S + cut + UNLOAD_S)
    terms = phys.terms(["tiny"] * 3, config.parts)
    assert terms == pytest.approx({"robot": robot, "cnc1": cnc1, "cnc2": cnc2})
    assert phys.bound(["tiny"] * 3, config.parts) == pytest.approx(max(robot, cnc1, cnc2))
    # The factory's bound of one such cell is the same figure, and zero for nothing to do.
    one = physical_bound(config.parts, phys)
    assert one({"tiny": 3}) == pytest.approx(max(robot, cnc1, cnc2))
    assert one({"tiny": 0}) == 0.0
    # Two cells alike share 5 parts 3 + 2: the larger share's bound (CNC 1's, here).
    assert cnc1 > max(robot, cnc2)
    best, split = split_bound({"a": one, "b": one}, {"tiny": 5})
    assert best == pytest.approx(cnc1)
    assert sorted(s["tiny"] for s in split.values()) == [2, 3]


async def test_the_emulated_mill_cuts_for_the_time_the_bound_counts(tiny_cell: Path) -> None:
    # The mill emulator runs the same DYNALAN model: its own log of the cut says 6 s too.
    config = load_cell(tiny_cell)
    mill_config = config.mills[0]
    emulator = Dyna2400Emulator(
        time_scale=1000.0, delays=OperatorDelays(power_on=1.0, keys=1.0, setup=20.0)
    )
    line = LineSettings(115200, 8, "N", 1)
    server = await serve(emulator, "rfc2217://127.0.0.1:0", line)
    mill = await Dyna2400Mill.connect(server.url, name="cnc1", settings=line)
    try:
        assert mill_config.setup is not None
        await mill.initialize(mill_config.setup)
        await mill._ready.wait(True, 5)
        await mill.download(tiny_cell / "programs" / "tiny_a.dyn")
    finally:
        await mill.close()
        await server.close()
    cut = physical_durations(config).machining[("cnc1", "tiny_a")].parts["cut"]
    assert [run.outcome for run in emulator.runs][-1] == "block end"
    assert emulator.runs[-1].machining_s == pytest.approx(CUT_S)
    assert cut == pytest.approx(CUT_S)
