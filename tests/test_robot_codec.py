"""Robot record codec: whole, split, byte-wise, after garbage, bad records; program files."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cellctl.errors import ChecksumError, FramingError, ProtocolError, UsageError
from cellctl.kinds.ibm7545.records import (
    END_GOOD,
    END_RECORD,
    DiDo,
    ExecuteOperand,
    MachineStatus,
    ProgramFile,
    ReadOperand,
    Record,
    checksum,
    decode_operand,
    decode_record,
    encode_operand,
    encode_record,
    reject_message,
    resync,
    select_application_operand,
)

SPEC_STATUS = b"D02044044\r\n"  # the source's machine-status example
SPEC_REJECT = b"D014040\r\n"  # the source's reject-status example


def decode_all(stream: bytes) -> list[Record]:
    """Feed ``stream`` as it would arrive and collect every record, like a driver would."""
    buf = bytearray()
    out: list[Record] = []
    for byte in stream:
        buf.append(byte)
        while True:
            rec, used = decode_record(buf)
            if not used:
                break
            del buf[:used]
            if rec is not None:
                out.append(rec)
    assert not buf.strip(b"\0")
    return out


def test_spec_examples_byte_for_byte() -> None:
    assert encode_record(Record("D", b"\x04\x40")) == SPEC_STATUS
    assert encode_record(Record("D", b"\x40")) == SPEC_REJECT
    assert decode_record(SPEC_STATUS) == (Record("D", b"\x04\x40"), len(SPEC_STATUS))
    assert decode_record(SPEC_REJECT) == (Record("D", b"\x40"), len(SPEC_REJECT))


def test_checksum_is_sum_mod_256() -> None:
    assert checksum(b"\x04\x40") == 0x44
    assert checksum(b"\xff\x02") == 0x01
    assert checksum(b"") == 0


def test_whole_record_then_more() -> None:
    rec, used = decode_record(SPEC_STATUS + b"EG\r\n")
    assert rec == Record("D", b"\x04\x40")
    assert used == len(SPEC_STATUS)


@pytest.mark.parametrize("cut", range(1, len(SPEC_STATUS)))
def test_split_in_two_at_every_position(cut: int) -> None:
    first = SPEC_STATUS[:cut]
    assert decode_record(first) == (None, 0)
    assert decode_record(first + SPEC_STATUS[cut:]) == (Record("D", b"\x04\x40"), 11)


def test_byte_by_byte() -> None:
    stream = SPEC_STATUS + b"EG\r\n" + SPEC_REJECT
    assert decode_all(stream) == [Record("D", b"\x04\x40"), END_GOOD, Record("D", b"\x40")]


def test_end_good_record() -> None:
    assert encode_record(END_GOOD) == b"EG\r\n"
    assert decode_record(b"EG\r\n") == (END_GOOD, 4)
    assert decode_record(b"EG\r") == (None, 0)
    assert END_GOOD.is_end_good
    assert not END_RECORD.is_end_good


def test_garbage_before_record_is_skipped_and_counted() -> None:
    # operand echo and NULs, as the source's listing skips before the D record
    stream = b"\x0001\r\n\x00" + SPEC_STATUS
    rec, used = decode_record(stream)
    assert rec is None
    assert used == 6
    assert decode_record(stream[used:]) == (Record("D", b"\x04\x40"), 11)
    assert decode_all(stream) == [Record("D", b"\x04\x40")]


def test_only_garbage_is_all_used() -> None:
    assert decode_record(b"\x00\x00\r\n") == (None, 4)
    assert decode_record(b"") == (None, 0)


def test_bad_checksum_carries_raw_bytes() -> None:
    bad = b"D02044045\r\n"
    with pytest.raises(ChecksumError) as info:
        decode_record(bad)
    assert info.value.raw == bad
    assert "44" in str(info.value) and "45" in str(info.value)
    assert isinstance(info.value, ProtocolError)


@pytest.mark.parametrize(
    "bad",
    [b"D0Z", b"D0204G", b"D02044g", b"DX", b"D0204\x00"],
)
def test_bad_hex_is_reported_as_soon_as_it_arrives(bad: bytes) -> None:
    with pytest.raises(FramingError) as info:
        decode_record(bad)
    assert info.value.raw == bad


@pytest.mark.parametrize(
    "bad",
    [
        b"D030440\r\n",  # says 3 bytes, has 1 and a checksum
        b"D0104404\r\n",  # says 1 byte, has more
        b"D01404040\r\n",
    ],
)
def test_wrong_byte_count(bad: bytes) -> None:
    with pytest.raises(FramingError, match="byte count") as info:
        decode_record(bad)
    assert bytes(info.value.raw) in bad


def test_missing_cr_lf() -> None:
    with pytest.raises(FramingError, match="CR LF"):
        decode_record(b"D014040XY")
    with pytest.raises(FramingError, match="CR LF"):
        decode_record(b"D014040\rX")
    with pytest.raises(FramingError, match="CR LF"):
        decode_record(b"EG\n\n")


def test_lf_cr_accepted_as_the_prose_writes_it() -> None:
    assert decode_record(b"D014040\n\r") == (Record("D", b"\x40"), 9)


def test_resync_after_error_drops_the_bad_record() -> None:
    stream = b"D02044045\r\n" + SPEC_REJECT
    with pytest.raises(ChecksumError):
        decode_record(stream)
    drop = resync(stream)
    assert decode_record(stream[drop:]) == (Record("D", b"\x40"), len(SPEC_REJECT))
    assert resync(b"D0") == 2


@given(
    ident=st.sampled_from("DN"),
    data=st.binary(max_size=255),
    lower=st.booleans(),
    garbage=st.binary(max_size=8).map(lambda b: bytes(x for x in b if x not in b"DEN")),
)
def test_round_trip(ident: str, data: bytes, lower: bool, garbage: bytes) -> None:
    rec = Record(ident, data)
    wire = encode_record(rec)
    if lower:  # hex digits in either case decode the same
        wire = wire[:1] + wire[1:].lower()
    assert decode_all(garbage + wire) == [rec]


def test_record_rejects_bad_identifier_and_size() -> None:
    with pytest.raises(UsageError):
        Record("DD", b"")
    with pytest.raises(UsageError):
        Record("d", b"")
    with pytest.raises(UsageError):
        Record("D", bytes(256))


# --- operands ------------------------------------------------------------------------------------


def test_operands_are_two_decimal_digits() -> None:
    assert encode_operand(ReadOperand.MACHINE_STATUS) == b"01\r\n"
    assert encode_operand(ReadOperand.DIDO) == b"10\r\n"
    assert encode_operand(ExecuteOperand.RETURN_HOME) == b"11\r\n"
    assert encode_operand(select_application_operand(3)) == b"33\r\n"
    assert [select_application_operand(n) for n in range(1, 6)] == [31, 32, 33, 34, 35]
    with pytest.raises(UsageError):
        encode_operand(100)
    with pytest.raises(UsageError):
        select_application_operand(6)


def test_decode_operand_incrementally() -> None:
    assert decode_operand(b"2") == (None, 0)
    assert decode_operand(b"22\r") == (None, 0)
    assert decode_operand(b"22\r\nX") == (22, 4)
    with pytest.raises(FramingError):
        decode_operand(b"2A")
    with pytest.raises(FramingError):
        decode_operand(b"223")


# --- status payloads -----------------------------------------------------------------------------


def test_machine_status_decodes_the_spec_example() -> None:
    status = MachineStatus.from_bytes(b"\x04\x40")
    assert not status.ok
    assert status.conditions == ("data error: point out of workspace",)
    assert status.to_bytes() == b"\x04\x40"


def test_machine_status_several_flags() -> None:
    status = MachineStatus.from_bytes(bytes([128 | 8, 0]))
    assert status.conditions == ("servo error", "transmission error")
    assert str(MachineStatus()) == "no machine status error"
    assert MachineStatus().ok
    with pytest.raises(FramingError):
        MachineStatus.from_bytes(b"\x00")


def test_reject_messages() -> None:
    assert reject_message(48) == "improper startup sequence"
    assert reject_message(83) == "invalid application number"
    assert reject_message(16) == "record format error"
    assert reject_message(112) == "Xoff time out (30 seconds)"
    assert "99" in reject_message(99)


def test_dido_bit_layout() -> None:
    # inputs 1 and 9 on, outputs 8 and 16 on
    dido = DiDo.from_bytes(b"\x01\x01\x80\x80")
    assert dido.input(1) and dido.input(9) and not dido.input(2)
    assert dido.output(8) and dido.output(16) and not dido.output(1)
    assert dido.to_bytes() == b"\x01\x01\x80\x80"
    with pytest.raises(UsageError):
        dido.input(17)
    with pytest.raises(FramingError):
        DiDo.from_bytes(b"\x00")


@given(st.integers(0, 0xFFFF), st.integers(0, 0xFFFF))
def test_dido_round_trip(inputs: int, outputs: int) -> None:
    assert DiDo.from_bytes(DiDo(inputs, outputs).to_bytes()) == DiDo(inputs, outputs)


# --- program files -------------------------------------------------------------------------------


def nibble_patch(line: str, partition: int) -> str:
    """The source's patch: character 5 = partition digit, character 23 = fixed letter B..F."""
    chars = list(line)
    chars[4] = str(partition)
    chars[22] = "BCDEF"[partition - 1]
    return "".join(chars)


def test_partition_patch_recomputes_the_whole_checksum_across_a_carry() -> None:
    # Name bytes sum to 0x?E, so partition 1 ends the checksum in F and moving to partition 2
    # carries into the high digit, which the source's nibble patch never touches.
    prog = ProgramFile.build("AAAAAAH", 1, [Record("D", b"\x0a")])
    header = prog.to_text().splitlines()[0]
    assert header == "N09014141414141414820EF"
    moved = prog.with_partition(2)
    line = moved.to_text().splitlines()[0]
    assert line == "N09024141414141414820F0"
    assert moved.partition == 2
    assert nibble_patch(header, 2) == "N09024141414141414820EC"  # the source: wrong
    assert decode_record(line.encode() + b"\r\n") == (moved.records[0], len(line) + 2)


def test_with_partition_keeps_body_and_name() -> None:
    prog = ProgramFile.build("xfer1", 1, [Record("D", b"\x0a")])
    moved = prog.with_partition(5)
    assert moved.name == "XFER1"
    assert moved.body == prog.body
    assert moved.records[-1] == END_RECORD
    with pytest.raises(UsageError):
        prog.with_partition(0)


def test_program_file_round_trip(tmp_path: Path) -> None:
    prog = ProgramFile.build("PICK", 3, [Record("D", b"\x05"), Record("D", b"\x0a")])
    path = tmp_path / "pick.rec"
    path.write_text(prog.to_text())
    loaded = ProgramFile.load(path)
    assert loaded.records == prog.records
    assert loaded.partition == 3
    assert loaded.name == "PICK"
    assert loaded.to_text().splitlines() == [
        "N09035049434B20202020AA",
        "D010505",
        "D010A0A",
        "E0000",
    ]


GOOD = "N09015846455231202020C7\nD010A0A\nE0000\n"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty program"),
        ("D010A0A\nE0000\n", "line 1: first record must be the N record"),
        ("N010101\nE0000\n", "line 1: N record must have 9 data bytes"),
        ("N09065846455231202020CC\nE0000\n", "partition must be 01..05"),
        ("N09015846455231202020C7\nD010A0A\n", "line 2: last record must be the end record"),
        ("N09015846455231202020C7\n\nN010101\nE0000\n", "line 3: expected a D record"),
        ("N09015846455231202020C8\nE0000\n", "line 1: bad checksum"),
        ("N09015846455231202020C7\nD01ZZ0A\nE0000\n", "line 2: bad hex"),
        ("N09015846455231202020C7\nhello\nE0000\n", "line 2: not a record"),
        ("N09015846455231202020C7\nD010A0A extra\nE0000\n", "line 2"),
    ],
)
def test_malformed_program_files_name_file_line_and_fault(text: str, message: str) -> None:
    with pytest.raises(UsageError, match=message) as info:
        ProgramFile.parse(text, "prog.rec")
    assert str(info.value).startswith("prog.rec")


def test_good_program_text_parses_with_crlf_and_blank_lines() -> None:
    prog = ProgramFile.parse(GOOD.replace("\n", "\r\n") + "\n\n", "prog.rec")
    assert prog.name == "XFER1"
    assert len(prog.body) == 1


def test_missing_program_file_is_a_usage_error(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match=r"nofile\.rec"):
        ProgramFile.load(tmp_path / "nofile.rec")


def test_program_build_checks_name_and_partition() -> None:
    with pytest.raises(UsageError, match="partition"):
        ProgramFile.build("X", 6, [])
    with pytest.raises(UsageError, match="name"):
        ProgramFile.build("TOOLONGNAME", 1, [])
    with pytest.raises(UsageError, match="name"):
        ProgramFile.build("", 1, [])
