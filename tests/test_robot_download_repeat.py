"""The robot driver sends one program again and again, as a DNC server does: every download
carries the same bytes as the first, aimed at the partition asked for each time."""

from __future__ import annotations

from cellctl.drivers.robot import Ibm7545Robot
from cellctl.emulators.robot import Ibm7545Emulator
from cellctl.emulators.serve import serve
from cellctl.link import ROBOT_LINE
from cellctl.protocol.aml import compile_source
from cellctl.protocol.robot import ProgramFile, Record, encode_record
from cellctl.testing import expected_exchange

ACK = b"\x06"


def _program(name: str = "DEMO") -> ProgramFile:
    return ProgramFile.build(name, 1, [Record("D", b"\x01\x02"), Record("D", b"\xff")])


def _script(prog: ProgramFile, partition: int) -> list[tuple[bytes, bytes]]:
    n = encode_record(prog.with_partition(partition).records[0])
    return [
        (b"N", ACK),
        (n[1:], ACK),
        (b"D02010203\r\n", ACK),
        (b"D01FFFF\r\n", ACK),
        (b"E0000\r\n", ACK),
    ]


async def test_same_program_to_partitions_3_1_3_sends_each_partitions_bytes() -> None:
    prog = _program()
    other = _program("OTHER")
    script = _script(prog, 3) + _script(prog, 1) + _script(prog, 3) + _script(other, 3)
    # partition 3's N record as the spec example spells it, not from the codec
    assert script[1][0] == b"090344454D4F20202020A8\r\n"
    async with expected_exchange(script) as link:
        robot = Ibm7545Robot(link)
        robot.state = 1
        for partition in (3, 1, 3):
            await robot.download(partition, prog)
        assert robot.holds(3, prog) and robot.holds(1, prog)
        await robot.download(3, other)
    assert robot.partitions == {1: "DEMO", 2: None, 3: "OTHER", 4: None, 5: None}
    assert robot.holds(3, other) and not robot.holds(3, prog)


async def test_repeated_downloads_reach_the_emulator_whole() -> None:
    emulator = Ibm7545Emulator(time_scale=500.0)
    server = await serve(emulator, "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    prog = compile_source("PMOVE(PT(300, 0, 0, 0))\nDELAY(0)\nEND", "DEMO", 1)
    try:
        async with await Ibm7545Robot.connect(server.url) as robot:
            await robot.initialize()
            for partition in (2, 5, 2):
                await robot.download(partition, prog)
    finally:
        await server.close()
    loaded = {p: emulator.partitions[p] for p in (2, 5)}
    assert all(program is not None for program in loaded.values())
    assert loaded[2].name == loaded[5].name == "DEMO"  # type: ignore[union-attr]
    assert [p for p, program in emulator.partitions.items() if program] == [2, 5]
