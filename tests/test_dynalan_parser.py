"""DYNALAN parser and wire framing: the source's examples, every statement, bad spellings."""

from __future__ import annotations

import pytest

from cellctl.kinds.dyna2400.dynalan import (
    END_OF_TRANSMISSION,
    STATEMENTS,
    Kind,
    Origin,
    Units,
    decode_line,
    parse_line,
    parse_program,
)

SETUP = """000 START INS 01
001 TD = .125
002 FR XYZ = 10.0
003 SETUP >zcxyu
004 SKIP TO 900
900
"""

MILLING = """000 GO X 1.000
001   Y 1.000
003 GO X 1.100
004 GR X 2.000
005 SKIP TO 900
900
"""


def test_source_setup_program_parses_to_typed_statements() -> None:
    program = parse_program(SETUP)
    assert program.ok
    assert program.units is Units.INS
    kinds = [line.kind for line in program.lines]
    assert kinds == [Kind.START, Kind.TD, Kind.FEED, Kind.SETUP, Kind.SKIP, Kind.BLANK]
    feed = program.lines[2].statement
    assert feed is not None
    assert feed.value("rate") == 10.0 and feed.text["axes"] == "XYZ"
    assert program.lines[1].statement is not None
    assert program.lines[1].statement.value("diameter") == 0.125


def test_source_milling_program_keeps_numbers_as_written() -> None:
    program = parse_program(MILLING)
    assert [line.number for line in program.lines] == [0, 1, 3, 4, 5, 900]
    continuation = program.lines[1].statement
    assert continuation is not None
    assert continuation.kind is Kind.AXIS and continuation.words == (("Y", 1.0),)
    assert program.block_count == 1


@pytest.mark.parametrize(
    ("text", "kind"),
    [
        ("TOOL 02", Kind.TOOL),
        ("F XYZ = 8", Kind.FEED),
        ("FR Z = 4.0", Kind.FEED),
        ("GOf X .5", Kind.GO_FAST),
        ("GRf Z 1.0", Kind.GR_FAST),
        ("GR A -90", Kind.ARC),
        ("Z>C", Kind.CLEARANCE),
        ("ZERO AT", Kind.ZERO_AT),
        (">REF COORD", Kind.REF_COORD),
        ("SPINDLE ON", Kind.SPINDLE_ON),
        ("SPINDLE OFF", Kind.SPINDLE_OFF),
        ("SP= 9000 RPM", Kind.SPINDLE_SPEED),
        ("COOLANT ON", Kind.COOLANT_ON),
        ("COOLANT OFF", Kind.COOLANT_OFF),
        ("DWELL 2.5", Kind.DWELL),
        ("DRIL PECK= .100", Kind.DRILL),
        ("ZH= 0", Kind.DRILL_TOP),
        ("ZD= -.5", Kind.DRILL_BOTTOM),
        ("REPEAT 04", Kind.REPEAT),
        ("REPEAT END", Kind.REPEAT_END),
        ("HALT", Kind.HALT),
        ("END", Kind.END),
        ("; ROUGH THE BASE, TOOL 1", Kind.COMMENT),
        ("MILL X= 1 Y= 2 ZD= -.2", Kind.MILL),
        ("FRAME XL= 1 YL= 2 ZD= -.2 DP= .1", Kind.FRAME),
        ("RFRAME XL= 1 YL= 2 ZD= -.2", Kind.RFRAME),
        ("RPOCKET XL= 1 YL= 2 ZD= -.2", Kind.RPOCKET),
        ("CPOCKET R= .5 ZD= -.2", Kind.CPOCKET),
        ("ARCFRAME R= .5 A= 270 AS= 45 ZD= -.1", Kind.ARCFRAME),
    ],
)
def test_every_statement_of_the_table_parses(text: str, kind: Kind) -> None:
    number, statement, findings = parse_line(f"010 {text}")
    assert findings == []
    assert number == 10
    assert statement is not None and statement.kind is kind


def test_table_marks_the_canned_cycles_as_the_projects_own() -> None:
    origins = {spec.kind: spec.origin for spec in STATEMENTS}
    for kind in (Kind.MILL, Kind.FRAME, Kind.RFRAME, Kind.RPOCKET, Kind.CPOCKET, Kind.ARCFRAME):
        assert origins[kind] is Origin.PROJECT
    assert origins[Kind.START] is Origin.SOURCE
    assert origins[Kind.DRILL] is Origin.DOCUMENTED


@pytest.mark.parametrize(
    ("line", "column", "code"),
    [
        ("005 MOVE X 1", 5, "unknown-statement"),
        ("005 go X 1", 5, "unknown-statement"),
        ("005 GO X 1.2.3", 10, "bad-number"),
        ("005 FR XYZ = ten", 14, "bad-number"),
        ("005 SKIP TO 9", 13, "bad-number"),
        ("005 START IN 01", 11, "syntax"),
        ("005 SETUP >abc", 12, "syntax"),
        ("005 GO Q 1", 8, "axis-words"),
        ("005 GO", 5, "axis-words"),
        ("005 ; bad", 7, "comment"),
        ("5 GO X 1", 1, "line-number"),
        ("0005 GO X 1", 1, "line-number"),
        ("005GO X 1", 4, "line-number"),
        ("GO X 1", 1, "line-number"),
        ("005 RPOCKET XL= 1 ZD= -.1", 5, "syntax"),
        ("005 MILL X= 1 Y= 1 ZD= -.1 Q= 2", 28, "syntax"),
    ],
)
def test_bad_lines_report_column_and_code(line: str, column: int, code: str) -> None:
    _, statement, findings = parse_line(line)
    assert statement is None
    assert findings[0][0] == column
    assert findings[0][1] == code


def test_blocks_of_a_file_are_counted_at_each_900_line() -> None:
    program = parse_program(SETUP + MILLING + MILLING)
    assert program.block_count == 3
    assert program.lines[-1].block == 3


# ---- wire framing ---------------------------------------------------------------------------
def _decode_all(data: bytes) -> list[object]:
    items: list[object] = []
    buffer = bytearray(data)
    while True:
        used, item = decode_line(buffer)
        if used == 0:
            break
        del buffer[:used]
        if item is not None:
            items.append(item)
    return items


@pytest.mark.parametrize("ending", [b"\r\n", b"\n\r", b"\n"])
def test_controller_accepts_crlf_lfcr_and_lf(ending: bytes) -> None:
    data = b"000 GO X 1.000" + ending + b"900" + ending + b"\x1a"
    assert _decode_all(data) == [b"000 GO X 1.000", b"900", END_OF_TRANSMISSION]


def test_decode_whole_split_and_byte_by_byte_agree() -> None:
    data = SETUP.replace("\n", "\r\n").encode() + b"\x1a"
    whole = _decode_all(data)
    for cut in range(len(data)):
        buffer = bytearray()
        items: list[object] = []
        for piece in (data[:cut], data[cut:]):
            buffer += piece
            while (result := decode_line(buffer))[0]:
                del buffer[: result[0]]
                if result[1] is not None:
                    items.append(result[1])
        assert items == whole
    assert len(whole) == 7


def test_decode_needs_more_without_a_terminator() -> None:
    assert decode_line(b"000 GO X") == (0, None)
    assert decode_line(b"000 END\x1a") == (7, b"000 END")
