"""Byte-exact robot driver tests: the exchanges of the spec, replayed with expected_exchange."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.drivers.state import StateStore
from cellctl.errors import ChecksumError, DeviceError, LinkTimeout, UnexpectedReply, UsageError
from cellctl.kinds.ibm7545.driver import Ibm7545Robot, RobotConfig
from cellctl.kinds.ibm7545.records import ProgramFile, Record
from cellctl.testing import expected_exchange

XOFF, XON, ACK, EOT = b"\x13", b"\x11", b"\x06", b"\x04"
READY = XOFF + XON


def read_script(operand: bytes, record: bytes) -> list[tuple[bytes, bytes]]:
    """R transaction: R, Xoff Xon, operand, D record, Ack, EG, Ack."""
    return [(b"R", READY), (operand + b"\r\n", record), (ACK, b"EG\r\n"), (ACK, b"")]


def execute_script(operand: bytes, done: bytes = ACK) -> list[tuple[bytes, bytes]]:
    return [(b"X", READY), (operand + b"\r\n", done)]


def reject_script(code_record: bytes) -> list[tuple[bytes, bytes]]:
    return read_script(b"02", code_record)


async def test_status_decodes_spec_example_point_out_of_workspace() -> None:
    async with expected_exchange(read_script(b"01", b"D02044044\r\n")) as link:
        status = await Ibm7545Robot(link).status()
    assert status.machine.flags == 0x04 and status.machine.data_error == 0x40
    assert status.machine.conditions == ("data error: point out of workspace",)


async def test_reject_status_spec_example() -> None:
    async with expected_exchange(read_script(b"02", b"D014040\r\n")) as link:
        code, message = await Ibm7545Robot(link).reject_status()
    assert (code, message) == (64, "point out of workspace")


async def test_d_record_after_echo_of_operand_is_found() -> None:
    script = read_script(b"01", b"01\r\n\x00D02000000\r\n")
    async with expected_exchange(script) as link:
        status = await Ibm7545Robot(link).status()
    assert status.machine.ok


async def test_io_decodes_inputs_and_outputs() -> None:
    # inputs 1 and 9 on, output 16 on: 01 01 00 80, checksum 82
    async with expected_exchange(read_script(b"10", b"D040101008082\r\n")) as link:
        dido = await Ibm7545Robot(link).io()
    assert dido.input(1) and dido.input(9) and not dido.input(2)
    assert dido.output(16) and not dido.output(1)


async def test_go_selects_application_then_starts_cycle(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.save("r1", {"state": 1, "partitions": {"3": "LOADCNC1"}})
    async with expected_exchange(execute_script(b"33") + execute_script(b"22")) as link:
        robot = Ibm7545Robot(link, name="r1", store=store)
        await robot.go(3)
    assert robot.state == 2
    assert Ibm7545Robot(link, name="r1", store=store).state == 2  # survives a restart


async def test_go_on_empty_partition_reads_reject_and_says_partition_empty() -> None:
    # The host thought partition 4 full (the controller lost it): reject 83 says otherwise.
    script = [(b"X", READY), (b"34\r\n", EOT), *reject_script(b"D015353\r\n")]
    async with expected_exchange(script) as link:
        robot = Ibm7545Robot(link)
        robot.state, robot.partitions[4] = 1, "LOADCNC1"
        with pytest.raises(DeviceError) as err:
            await robot.go(4)
    assert err.value.code == 83
    assert "partition empty" in str(err.value)
    assert robot.partitions[4] is None


async def test_start_before_initialize_is_improper_startup_sequence() -> None:
    """48 answers a start on a cold controller and a request while a cycle runs alike: the
    spec has no reject after which the controller forgot its state or its partitions, so the
    host keeps its view; the error says to initialize (the cell's recovery does)."""
    start = [(b"X", READY), (b"22\r\n", EOT)]
    script = [*execute_script(b"31"), *start, *reject_script(b"D013030\r\n")]
    async with expected_exchange(script) as link:
        robot = Ibm7545Robot(link)
        robot.state, robot.partitions[1] = 1, "LOADCNC1"  # the host's view, the controller cold
        with pytest.raises(DeviceError, match="improper startup sequence") as err:
            await robot.go(1)
    assert robot.state == 1 and robot.partitions[1] == "LOADCNC1"
    assert robot.needs_initialize(err.value)


async def test_initialize_return_home_waits_through_xoffs_for_xon() -> None:
    script = [(b"X", READY), (b"11\r\n", XOFF + XOFF + XON), *execute_script(b"20")]
    async with expected_exchange(script) as link:
        robot = Ibm7545Robot(link)
        await robot.initialize()
    assert robot.state == 1


@pytest.mark.parametrize("completion", [ACK, XOFF + XON], ids=["ack", "xoff-xon"])
async def test_stop_accepts_ack_or_xoff_then_xon(completion: bytes) -> None:
    async with expected_exchange(execute_script(b"23", completion)) as link:
        robot = Ibm7545Robot(link)
        robot.state = 2
        await robot.stop()
    assert robot.state == 1


async def test_halt_flushes_partitions(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.save("r1", {"state": 1, "partitions": {"2": "LOADCNC1"}})
    async with expected_exchange(execute_script(b"23")) as link:
        robot = Ibm7545Robot(link, name="r1", store=store)
        assert robot.partitions[2] == "LOADCNC1"
        await robot.halt()
    assert robot.state == 0 and not any(robot.partitions.values())


async def test_reset_errors_uses_configurable_operand() -> None:
    async with expected_exchange(execute_script(b"27")) as link:
        await Ibm7545Robot(link, config=RobotConfig(erreset_operand=27)).reset_errors()


def _program() -> ProgramFile:
    return ProgramFile.build("DEMO", 1, [Record("D", b"\x01\x02"), Record("D", b"\xff")])


async def test_download_sends_n_alone_then_each_record_with_ack() -> None:
    prog = _program()
    script = [
        (b"N", ACK),
        (b"090344454D4F20202020A8\r\n", ACK),  # partition patched to 3, checksum recomputed
        (b"D02010203\r\n", ACK),
        (b"D01FFFF\r\n", ACK),
        (b"E0000\r\n", ACK),
    ]
    seen: list[tuple[int, int]] = []
    async with expected_exchange(script) as link:
        robot = Ibm7545Robot(link)
        robot.state = 1
        await robot.download(3, prog, progress=lambda done, total, _b: seen.append((done, total)))
    assert robot.partitions[3] == "DEMO"
    assert robot.holds(3, prog)
    assert seen[-1] == (4, 4)


async def test_download_rejected_mid_way_leaves_partition_empty() -> None:
    script = [
        (b"N", ACK),
        (b"0902444", b""),
        (b"54D4F20202020A7\r\n", ACK),
        (b"D02010203\r\n", EOT),
        *reject_script(b"D015050\r\n"),
    ]
    async with expected_exchange(script) as link:
        robot = Ibm7545Robot(link)
        robot.state = 1
        with pytest.raises(DeviceError, match="insufficient memory"):
            await robot.download(2, _program())
    assert robot.partitions[2] is None


@pytest.mark.parametrize("partition", [0, 6, -1])
async def test_bad_partition_refused_before_any_byte(partition: int) -> None:
    async with expected_exchange([]) as link:
        robot = Ibm7545Robot(link)
        with pytest.raises(UsageError, match="partition"):
            await robot.download(partition, _program())
        with pytest.raises(UsageError, match="partition"):
            await robot.go(partition)


async def test_missing_or_malformed_program_refused_before_any_byte(tmp_path: Path) -> None:
    bad = tmp_path / "bad.rec"
    bad.write_text("D02010203\nE0000\n")
    async with expected_exchange([]) as link:
        robot = Ibm7545Robot(link)
        with pytest.raises(UsageError, match="cannot read"):
            await robot.download(1, tmp_path / "missing.rec")
        with pytest.raises(UsageError, match="N record"):
            await robot.download(1, bad)


async def test_bad_checksum_is_retried_then_counted() -> None:
    script = read_script(b"01", b"D02044045\r\n") + read_script(b"01", b"D02044044\r\n")
    async with expected_exchange(script) as link:
        robot = Ibm7545Robot(link)
        status = await robot.status()
    assert status.machine.data_error == 0x40
    assert robot.counters.checksum_retries == 1


async def test_bad_checksum_every_time_raises_with_raw_bytes() -> None:
    script = read_script(b"01", b"D02044045\r\n") * 2
    async with expected_exchange(script) as link:
        robot = Ibm7545Robot(link, config=RobotConfig(checksum_retries=1))
        with pytest.raises(ChecksumError) as err:
            await robot.status()
    assert err.value.raw == b"D02044045\r\n"


async def test_silence_raises_link_timeout() -> None:
    async with expected_exchange([(b"R", b"")]) as link:
        robot = Ibm7545Robot(link, config=RobotConfig(reply_timeout=0.05))
        with pytest.raises(LinkTimeout, match="no answer"):
            await robot.status()


async def test_xoff_then_silence_raises_after_busy_silence() -> None:
    async with expected_exchange([(b"X", XOFF + XOFF)]) as link:
        robot = Ibm7545Robot(link, config=RobotConfig(busy_silence=0.05))
        with pytest.raises(LinkTimeout, match="Xoff, then nothing"):
            await robot.auto_mode()


QUICK = RobotConfig(reply_timeout=0.05, retry_settle=0.01, checksum_retries=1)
BREAK = b"E\r\n"  # ends what the controller was receiving; its EOT is discarded


async def test_garbage_instead_of_xoff_every_time_is_unexpected_reply_with_raw() -> None:
    script = [(b"X", b"?"), (BREAK, EOT), (b"X", b"?")]
    async with expected_exchange(script) as link:
        with pytest.raises(UnexpectedReply) as err:
            await Ibm7545Robot(link, config=QUICK).auto_mode()
    assert err.value.raw == b"?"


async def test_a_garbled_handshake_is_tried_again_and_counted() -> None:
    script = [(b"R", XOFF + b"\x15"), (BREAK, EOT), *read_script(b"01", b"D02000000\r\n")]
    async with expected_exchange(script) as link:
        robot = Ibm7545Robot(link, config=QUICK)
        assert (await robot.machine_status()).ok
    assert robot.counters.handshake_retries == 1


async def test_bad_erreset_operand_is_refused_before_any_byte() -> None:
    async with expected_exchange([]) as link:
        robot = Ibm7545Robot(link, config=RobotConfig(erreset_operand=100))
        with pytest.raises(UsageError, match=r"operand must be 0\.\.99"):
            await robot.reset_errors()
    assert link.bytes_sent == 0
