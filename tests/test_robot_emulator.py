"""The robot emulator, driven with raw bytes over a real TCP connection (no driver)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable

import pytest

from cellctl.emulators.serve import Server, serve
from cellctl.errors import UsageError
from cellctl.kinds.ibm7545.aml import compile_source
from cellctl.kinds.ibm7545.emulator import FAULTS, Ibm7545Emulator
from cellctl.kinds.ibm7545.records import Record, encode_record
from cellctl.link import ROBOT_LINE

XOFF, XON, ACK, EOT = b"\x13", b"\x11", b"\x06", b"\x04"
WAIT_S = 5.0  # deadline for any one expected answer; never reached when things work


class RawHost:
    """A host that speaks bytes: send, and expect exact bytes back."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer

    async def send(self, data: bytes) -> None:
        self.writer.write(data)
        await self.writer.drain()

    async def expect(self, data: bytes) -> None:
        async with asyncio.timeout(WAIT_S):
            got = await self.reader.readexactly(len(data))
        assert got == data

    async def execute(self, operand: bytes, answer: bytes) -> None:
        """X transaction: identifier, Xoff Xon, operand, then ``answer``."""
        await self.send(b"X")
        await self.expect(XOFF + XON)
        await self.send(operand + b"\r\n")
        await self.expect(answer)

    async def read(self, operand: bytes, record: bytes) -> None:
        """R transaction, answered with the exact D ``record`` (CR LF added), acknowledged."""
        await self.send(b"R")
        await self.expect(XOFF + XON)
        await self.send(operand + b"\r\n")
        await self.expect(record + b"\r\n")
        await self.send(ACK)
        await self.expect(b"EG\r\n")
        await self.send(ACK)

    async def reject_status(self, code: int) -> None:
        await self.read(b"02", encode_record_text(bytes([code])))

    async def initialize(self) -> None:
        await self.execute(b"11", XOFF + XON)
        await self.execute(b"20", ACK)

    async def download(self, source: str, name: str, partition: int) -> None:
        prog = compile_source(source, name, partition)
        lines = [encode_record(r) for r in prog.records]
        await self.send(b"N")
        await self.expect(ACK)
        for wire in [lines[0][1:], *lines[1:]]:
            await self.send(wire)
            await self.expect(ACK)

    async def closed(self) -> bool:
        async with asyncio.timeout(WAIT_S):
            return await self.reader.read(1) == b""

    async def close(self) -> None:
        self.writer.close()
        await self.writer.wait_closed()


def encode_record_text(data: bytes) -> bytes:
    return encode_record(Record("D", data))[:-2]


async def poll(condition: Callable[[], bool]) -> None:
    """Wait until ``condition()`` holds (deadline WAIT_S)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + WAIT_S
    while not condition():
        assert loop.time() < deadline, "condition not reached in time"
        await asyncio.sleep(0.005)


@pytest.fixture
def robot() -> Ibm7545Emulator:
    return Ibm7545Emulator(time_scale=200.0)


@pytest.fixture
async def server(robot: Ibm7545Emulator) -> AsyncIterator[Server]:
    srv = await serve(robot, "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    yield srv
    await srv.close()


async def connect(server: Server) -> RawHost:
    host, port = server.url.removeprefix("socket://").rsplit(":", 1)
    reader, writer = await asyncio.open_connection(host, int(port))
    return RawHost(reader, writer)


@pytest.fixture
async def host(server: Server) -> AsyncIterator[RawHost]:
    h = await connect(server)
    yield h
    await h.close()


PICK = """\
PMOVE(PT(500, -300, 0, 0))
DOWN
GRASP
UP
WRITEO(5, 1)
DELAY(0.5)
RELEASE
END
"""

WAIT_FOR_INPUT = """\
WAITI(3, 1)
WRITEO(7, 1)
END
"""


# --- X: execute ----------------------------------------------------------------------------------


async def test_initialize_reaches_state_1(host: RawHost, robot: Ibm7545Emulator) -> None:
    await host.execute(b"11", XOFF + XON)  # return home: Xoff at once, Xon when home
    assert robot.state == 0 and robot.homed
    await host.execute(b"20", ACK)
    assert robot.state == 1


async def test_return_home_repeats_xoff_while_moving(server: Server) -> None:
    robot = server.device
    assert isinstance(robot, Ibm7545Emulator)
    robot.xoff_repeat_s = 0.25
    robot.position = (150.0, 0.0, 0.0, 0.0)  # 500 mm from home: 1 s of machine time
    host = await connect(server)
    await host.execute(b"11", XOFF + XOFF * 3 + XON)
    assert robot.position == robot.arm.home
    await host.close()


async def test_auto_before_return_home_is_improper_startup(host: RawHost) -> None:
    await host.execute(b"20", EOT)
    await host.reject_status(48)


async def test_start_before_initialize_is_improper_startup(host: RawHost) -> None:
    await host.execute(b"22", EOT)
    await host.reject_status(48)


async def test_select_empty_partition_is_invalid_application(host: RawHost) -> None:
    await host.initialize()
    await host.execute(b"33", EOT)
    await host.reject_status(83)


async def test_unknown_operand_is_undefined_record(host: RawHost) -> None:
    await host.execute(b"99", EOT)
    await host.reject_status(32)


async def test_malformed_operand_is_record_format_error(host: RawHost) -> None:
    await host.execute(b"1X", EOT)
    await host.reject_status(16)


async def test_unknown_identifier_is_rejected(host: RawHost) -> None:
    await host.send(b"Q")
    await host.expect(EOT)
    await host.reject_status(96)


async def test_silent_host_times_out_with_reject_112(server: Server) -> None:
    robot = server.device
    assert isinstance(robot, Ibm7545Emulator)
    robot.host_timeout_s = 10.0  # 50 ms at time scale 200: the 1 s floor
    host = await connect(server)
    await host.send(b"X")
    await host.expect(XOFF + XON + EOT)
    await host.reject_status(112)
    await host.close()


async def test_host_that_does_not_ack_the_d_record_times_out(server: Server) -> None:
    robot = server.device
    assert isinstance(robot, Ibm7545Emulator)
    robot.host_timeout_s = 10.0
    host = await connect(server)
    await host.send(b"R")
    await host.expect(XOFF + XON)
    await host.send(b"01\r\n")
    await host.expect(b"D0200000" + b"0\r\n" + EOT)
    await host.reject_status(112)
    await host.close()


async def test_erreset_clears_reject_status(host: RawHost) -> None:
    await host.execute(b"22", EOT)
    await host.execute(b"24", ACK)
    await host.reject_status(0)


async def test_erreset_operand_is_configurable() -> None:
    robot = Ibm7545Emulator(time_scale=200.0, erreset_operand=25)
    srv = await serve(robot, "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    host = await connect(srv)
    await host.execute(b"22", EOT)
    await host.execute(b"24", EOT)  # now an undefined operand
    await host.execute(b"25", ACK)
    await host.reject_status(0)
    await host.close()
    await srv.close()


# --- R: read -------------------------------------------------------------------------------------


async def test_read_machine_status_when_all_is_well(host: RawHost) -> None:
    await host.read(b"01", b"D0200000" + b"0")


async def test_read_dido_status_layout(host: RawHost, robot: Ibm7545Emulator) -> None:
    robot.set_input(1, True)
    robot.set_input(9, True)
    await host.read(b"10", b"D04" + b"01010000" + b"02")


async def test_an_output_set_from_outside_is_read_and_heard(
    host: RawHost, robot: Ibm7545Emulator
) -> None:
    heard: list[tuple[int, bool]] = []
    robot.output_hooks.append(lambda port, value: heard.append((port, value)))
    robot.set_output(2, True)
    robot.set_output(2, True)  # no change: nothing heard
    await host.read(b"10", b"D04" + b"00000200" + b"02")
    assert heard == [(2, True)]
    for port in (0, 17):
        with pytest.raises(UsageError, match=r"output port must be 1\.\.16"):
            robot.set_output(port, True)
        with pytest.raises(UsageError, match=r"input port must be 1\.\.16"):
            robot.set_input(port, True)


async def test_read_unknown_operand_is_undefined_record(host: RawHost) -> None:
    await host.send(b"R")
    await host.expect(XOFF + XON)
    await host.send(b"07\r\n")
    await host.expect(EOT)
    await host.reject_status(32)


# --- N: download, and program execution ---------------------------------------------------------


async def test_download_acks_every_record_and_fills_the_partition(
    host: RawHost, robot: Ibm7545Emulator
) -> None:
    await host.initialize()
    await host.download(PICK, "PICK", 2)
    loaded = robot.partitions[2]
    assert loaded is not None and loaded.name == "PICK"
    assert len(loaded.instructions) == 8


async def test_download_before_initialize_is_improper_startup(host: RawHost) -> None:
    await host.send(b"N")
    await host.expect(EOT)
    await host.reject_status(48)


async def test_download_with_bad_checksum_is_record_format_error(host: RawHost) -> None:
    await host.initialize()
    await host.send(b"N")
    await host.expect(ACK)
    await host.send(b"09015846455231202020C7\r\n")
    await host.expect(ACK)
    await host.send(b"D010A0B\r\n")  # checksum should be 0A
    await host.expect(EOT)
    await host.reject_status(16)


async def test_download_to_partition_6_is_invalid_application(host: RawHost) -> None:
    await host.initialize()
    await host.send(b"N")
    await host.expect(ACK)
    await host.send(b"09065846455231202020CC\r\n")
    await host.expect(EOT)
    await host.reject_status(83)


async def test_download_of_a_non_d_record_is_record_format_error(host: RawHost) -> None:
    await host.initialize()
    await host.send(b"N")
    await host.expect(ACK)
    await host.send(b"09015846455231202020C7\r\n")
    await host.expect(ACK)
    await host.send(b"N0101" + b"01\r\n")
    await host.expect(EOT)
    await host.reject_status(16)


async def test_download_beyond_partition_memory_is_insufficient_memory() -> None:
    robot = Ibm7545Emulator(time_scale=200.0, max_instructions=2)
    srv = await serve(robot, "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    host = await connect(srv)
    await host.initialize()
    await host.send(b"N")
    await host.expect(ACK)
    await host.send(b"09015846455231202020C7\r\n")
    await host.expect(ACK)
    await host.send(b"D010303\r\n")
    await host.expect(ACK)
    await host.send(b"D010404\r\n")
    await host.expect(ACK)
    await host.send(b"D010A0A\r\n")
    await host.expect(EOT)
    await host.reject_status(80)
    await host.close()
    await srv.close()


async def test_program_runs_to_completion(host: RawHost, robot: Ibm7545Emulator) -> None:
    await host.initialize()
    await host.download(PICK, "PICK", 1)
    await host.execute(b"31", ACK)
    await host.execute(b"22", ACK)
    await poll(lambda: robot.runs[-1].outcome != "running")
    assert robot.state == 1
    [run] = robot.runs
    assert (run.partition, run.program, run.outcome) == (1, "PICK", "completed")
    assert run.end is not None and run.end >= run.start
    assert robot.position == (500.0, -300.0, 0.0, 0.0)
    assert robot.output(5)
    assert not robot.output(16)  # released
    assert not robot.output(15)  # up
    await host.read(b"01", b"D0200000" + b"0")


async def test_point_out_of_workspace_stops_with_the_spec_status(
    host: RawHost, robot: Ibm7545Emulator
) -> None:
    await host.initialize()
    await host.download("PMOVE(PT(1000, 0, 0, 0))\nGRASP\nEND\n", "FAR", 4)
    await host.execute(b"34", ACK)
    await host.execute(b"22", ACK)
    await poll(lambda: robot.runs[-1].outcome != "running")
    assert robot.runs[-1].outcome == "point out of workspace"
    assert not robot.output(16)  # never got to GRASP
    await host.read(b"01", b"D02044044")  # the source's example, byte for byte
    await host.execute(b"24", ACK)
    await host.read(b"01", b"D0200000" + b"0")


async def test_waiti_blocks_until_the_input_is_set(host: RawHost, robot: Ibm7545Emulator) -> None:
    await host.initialize()
    await host.download(WAIT_FOR_INPUT, "WAIT", 1)
    await host.execute(b"31", ACK)
    await host.execute(b"22", ACK)
    await host.read(b"10", b"D04" + b"00000000" + b"00")  # a full round trip later: still waiting
    assert robot.runs[-1].outcome == "running" and robot.state == 2
    robot.set_input(3, True)
    await poll(lambda: robot.runs[-1].outcome == "completed")
    await host.read(b"10", b"D04" + b"04004000" + b"44")  # input 3, output 7
    assert robot.state == 1


async def test_start_cycle_twice_is_improper_startup(host: RawHost) -> None:
    await host.initialize()
    await host.download(WAIT_FOR_INPUT, "WAIT", 1)
    await host.execute(b"31", ACK)
    await host.execute(b"22", ACK)
    await host.execute(b"22", EOT)
    await host.reject_status(48)


async def test_stop_cycle_answers_xoff_then_xon_and_returns_to_state_1(
    host: RawHost, robot: Ibm7545Emulator
) -> None:
    await host.initialize()
    await host.download(WAIT_FOR_INPUT, "WAIT", 1)
    await host.execute(b"31", ACK)
    await host.execute(b"22", ACK)
    await host.execute(b"23", XOFF + XON)
    assert robot.state == 1
    assert robot.runs[-1].outcome == "stopped"
    # the partition survives a stop: start again
    await host.execute(b"22", ACK)
    assert len(robot.runs) == 2


async def test_stop_when_idle_is_harmless(host: RawHost, robot: Ibm7545Emulator) -> None:
    await host.execute(b"23", XOFF + XON)
    assert robot.state == 0 and robot.runs == []


async def test_power_cycle_flushes_the_partitions(host: RawHost, robot: Ibm7545Emulator) -> None:
    await host.initialize()
    await host.download(PICK, "PICK", 1)
    robot.power_cycle()
    assert robot.state == 0
    await host.execute(b"31", EOT)
    await host.reject_status(83)


async def test_state_survives_a_reconnect(server: Server, robot: Ibm7545Emulator) -> None:
    first = await connect(server)
    await first.initialize()
    await first.close()
    second = await connect(server)
    await second.execute(b"22", EOT)  # state 1 kept, no partition selected
    await second.reject_status(83)
    assert robot.state == 1
    await second.close()


# --- fault switches ------------------------------------------------------------------------------


def test_fault_table_names_every_switch() -> None:
    assert set(FAULTS) == {
        "power-off",
        "servo-error",
        "corrupt-checksum",
        "drop",
        "silent",
        "noise",
    }
    robot = Ibm7545Emulator()
    with pytest.raises(UsageError, match="unknown fault"):
        robot.set_fault("melt")
    with pytest.raises(UsageError, match="count"):
        robot.set_fault("corrupt-checksum", "many")


async def test_power_off_rejects_requests_with_128(host: RawHost, robot: Ibm7545Emulator) -> None:
    robot.set_fault("power-off")
    await host.send(b"X")
    await host.expect(EOT)
    await host.send(b"N")
    await host.expect(EOT)
    await host.reject_status(128)  # reads still answer
    robot.clear_fault("power-off")
    await host.initialize()
    assert robot.state == 1


async def test_power_off_aborts_a_running_cycle(host: RawHost, robot: Ibm7545Emulator) -> None:
    await host.initialize()
    await host.download(WAIT_FOR_INPUT, "WAIT", 1)
    await host.execute(b"31", ACK)
    await host.execute(b"22", ACK)
    robot.set_fault("power-off")
    await poll(lambda: robot.runs[-1].outcome != "running")
    assert robot.runs[-1].outcome == "manipulator power off"
    assert robot.state == 0


async def test_servo_error_sets_status_and_refuses_motion(
    host: RawHost, robot: Ibm7545Emulator
) -> None:
    robot.set_fault("servo-error")
    await host.read(b"01", b"D02800080")
    await host.execute(b"11", EOT)
    await host.reject_status(128)
    robot.clear_fault("servo-error")
    await host.execute(b"24", ACK)
    await host.read(b"01", b"D0200000" + b"0")
    await host.initialize()


async def test_corrupt_checksum_spoils_the_next_n_d_records(
    host: RawHost, robot: Ibm7545Emulator
) -> None:
    robot.set_fault("corrupt-checksum", "2")
    await host.read(b"01", b"D02000001")
    await host.read(b"02", b"D010001")
    await host.read(b"01", b"D0200000" + b"0")  # back to good
    assert "corrupt-checksum" not in robot.faults


async def test_drop_closes_the_connection_at_the_next_request(
    server: Server, robot: Ibm7545Emulator
) -> None:
    host = await connect(server)
    await host.initialize()
    robot.set_fault("drop")
    await host.send(b"R")
    assert await host.closed()
    await host.close()
    again = await connect(server)  # the controller is still there, state kept
    await again.read(b"01", b"D0200000" + b"0")
    assert robot.state == 1
    await again.close()


async def test_silent_reads_but_never_answers(server: Server, robot: Ibm7545Emulator) -> None:
    host = await connect(server)
    robot.set_fault("silent")
    await host.send(b"X")
    await poll(lambda: server.current_line is not None)
    line = server.current_line
    assert line is not None
    await poll(lambda: line.bytes_in >= 1 and not line.pending())
    robot.clear_fault("silent")
    # the swallowed X left nothing behind: the next request is answered from its first byte
    await host.read(b"02", b"D0100" + b"00")
    await host.close()


async def test_paced_line_answers_the_same_bytes() -> None:
    robot = Ibm7545Emulator(time_scale=200.0)
    srv = await serve(robot, "socket://127.0.0.1:0", ROBOT_LINE)  # pacing on: 4800 baud
    host = await connect(srv)
    await host.initialize()
    await host.read(b"01", b"D0200000" + b"0")
    await host.close()
    await srv.close()


AML_AS_WRITTEN = """\
START: PMOVE(PT(500, -300, 0, 0)); SPEED(50); ZMOVE(120.5);  -- several statements, one line
       TESTI(3, 1, DONE); WRITEO(7, 1);
DONE:  END
"""


@pytest.mark.parametrize(("input_3", "output_7"), [(False, True), (True, False)])
async def test_speed_zmove_and_testi_run(
    host: RawHost, robot: Ibm7545Emulator, input_3: bool, output_7: bool
) -> None:
    robot.set_input(3, input_3)
    await host.initialize()
    await host.download(AML_AS_WRITTEN, "TESTI", 1)
    await host.execute(b"31", ACK)
    await host.execute(b"22", ACK)
    await poll(lambda: robot.runs[-1].outcome != "running")
    assert robot.runs[-1].outcome == "completed"
    assert robot.position == (500.0, -300.0, 120.5, 0.0)
    assert robot.speed_percent == 50
    assert robot.output(7) is output_7  # TESTI jumped over WRITEO when input 3 was on


async def test_a_jump_to_itself_keeps_the_controller_answering(
    host: RawHost, robot: Ibm7545Emulator
) -> None:
    await host.initialize()
    await host.download("HERE: BRANCH(HERE); END\n", "SPIN", 1)
    await host.execute(b"31", ACK)
    await host.execute(b"22", ACK)
    await host.read(b"01", b"D0200000" + b"0")  # answered while the program spins
    await host.execute(b"23", XOFF + XON)
    assert robot.runs[-1].outcome == "stopped"


def test_a_wait_on_one_input_stays_told_while_others_change() -> None:
    """A program in WAITI(1, 1) says so (``waiting_for``) until input 1 comes, however often
    other inputs change meanwhile (a door opening wakes the wait, which goes on waiting)."""
    from cellctl.clock import current_clock, run_virtual
    from tests.test_quiet_waits import running

    async def session() -> None:
        clock = current_clock()
        emulator = Ibm7545Emulator()
        async with running(emulator, "WRITEO(6, 0)\nWAITI(1, 1)\nWRITEO(6, 1)\nEND\n") as robot:
            await clock.sleep(0.5)
            assert emulator.waiting_for == (1, True)
            for port, value in ((2, True), (3, True), (2, False)):
                emulator.set_input(port, value)
                await clock.sleep(0.1)
                assert emulator.waiting_for == (1, True) and emulator.running
            emulator.set_input(1, True)
            await robot.wait_cycle_end(6, timeout=5)
            assert emulator.waiting_for is None

    run_virtual(session())
