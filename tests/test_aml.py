"""AML/E subset compiler: every statement, every error, the examples compile."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.errors import FramingError, UsageError
from cellctl.kinds.ibm7545.aml import (
    Instruction,
    Op,
    compile_program,
    compile_source,
    decode_program,
    encode_instruction,
)
from cellctl.kinds.ibm7545.records import ProgramFile, Record

EXAMPLES = Path(__file__).resolve().parent.parent / "examples" / "robot"

EVERY_STATEMENT = """\
-- every statement of the subset
START:  PMOVE(PT(500.0, -100.5, 50, 90))   -- a point
        delay(1.5);
        GRASP
        RELEASE
        UP
        DOWN
        WAITI(3, 1)
LOOP:   WRITEO(16, 0)
        BRANCH(loop)
        END
"""


def test_every_statement_compiles_to_its_instruction() -> None:
    assert [(i.op, i.operands) for i in compile_program(EVERY_STATEMENT)] == [
        (Op.PMOVE, (5000, -1005, 500, 900)),
        (Op.DELAY, (15,)),
        (Op.GRASP, ()),
        (Op.RELEASE, ()),
        (Op.UP, ()),
        (Op.DOWN, ()),
        (Op.WAITI, (3, 1)),
        (Op.WRITEO, (16, 0)),
        (Op.BRANCH, (7,)),
        (Op.END, ()),
    ]


def test_compile_source_builds_a_program_file_that_decodes_back() -> None:
    prog = compile_source(EVERY_STATEMENT, name="every", partition=2)
    assert prog.name == "EVERY"
    assert prog.partition == 2
    assert prog.body[0] == Record("D", bytes.fromhex("01 1388 FC13 01F4 0384"))
    reparsed = ProgramFile.parse(prog.to_text())
    decoded = decode_program(reparsed.body)
    assert [(i.op, i.operands) for i in decoded] == [
        (i.op, i.operands) for i in compile_program(EVERY_STATEMENT)
    ]


def test_labels_alone_on_a_line_and_forward_branches() -> None:
    text = "BRANCH(there)\nhere:\nthere: GRASP\nBRANCH(here)\nEND\n"
    ops = compile_program(text)
    assert [(i.op, i.operands) for i in ops] == [
        (Op.BRANCH, (1,)),
        (Op.GRASP, ()),
        (Op.BRANCH, (1,)),
        (Op.END, ()),
    ]


@pytest.mark.parametrize(
    ("text", "where", "message"),
    [
        ("MOVE(1)\nEND\n", "line 1, column 1", "unknown statement MOVE"),
        ("PMOVE(PT(1, 2, x, 4))\nEND\n", "line 1, column 16", "bad number for z"),
        ("PMOVE(PT(1, 2, 3))\nEND\n", "line 1, column 17", "expected ','"),
        ("PMOVE(1, 2, 3, 4)\nEND\n", "line 1, column 7", "PMOVE needs a point"),
        ("PMOVE(PT(1.25, 2, 3, 4))\nEND\n", "line 1, column 10", "more than one decimal"),
        ("PMOVE(PT(4000, 2, 3, 4))\nEND\n", "line 1, column 10", "out of range"),
        ("PMOVE(PT(1, 2, 3, 400))\nEND\n", "line 1, column 19", "roll"),
        ("  DELAY(-1)\nEND\n", "line 1, column 9", "out of range"),
        ("DELAY 1\nEND\n", "line 1, column 7", "expected '\\('"),
        ("WAITI(17, 1)\nEND\n", "line 1, column 7", "port 17 out of range"),
        ("WAITI(1.5, 1)\nEND\n", "line 1, column 7", "whole number"),
        ("WRITEO(2, 2)\nEND\n", "line 1, column 11", "value 2 out of range"),
        ("WRITEO(2)\nEND\n", "line 1, column 9", "expected ','"),
        ("BRANCH(nowhere)\nEND\n", "line 1, column 8", "undefined label NOWHERE"),
        ("BRANCH(12)\nEND\n", "line 1, column 8", "BRANCH needs a label"),
        ("a: GRASP\na: UP\nEND\n", "line 2, column 1", "label a defined twice"),
        ("GRASP UP\nEND\n", "line 1, column 7", "unexpected 'UP' after GRASP"),
        ("GRASP\n", "<aml>", "missing END"),
        ("END\nGRASP\n", "line 2, column 1", "statement after END"),
        ("END\nlate:\n", "line 2, column 1", "label late after END"),
        ("GRASP # x\nEND\n", "line 1, column 7", "unexpected character '#'"),
        ("(GRASP)\nEND\n", "line 1, column 1", "expected a statement"),
    ],
)
def test_errors_say_line_column_and_what(text: str, where: str, message: str) -> None:
    with pytest.raises(UsageError, match=message) as info:
        compile_program(text)
    assert where in str(info.value)


def test_compile_source_checks_name_and_partition() -> None:
    with pytest.raises(UsageError, match="partition"):
        compile_source("END\n", "X", partition=6)
    with pytest.raises(UsageError, match="name"):
        compile_source("END\n", "much too long", partition=1)


@pytest.mark.parametrize(
    "record",
    [
        Record("D", b"\x7f"),  # unknown opcode
        Record("D", b"\x01\x00"),  # PMOVE too short
        Record("D", b"\x09\x00\x05"),  # branch past the end
        Record("D", b"\x07\x11\x01"),  # WAITI port 17
        Record("N", b"\x01"),
        Record("D", b""),
    ],
)
def test_decode_program_refuses_bad_records(record: Record) -> None:
    with pytest.raises(FramingError):
        decode_program([record, encode_instruction(Instruction(Op.END))])


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.aml")), ids=lambda p: p.name)
def test_example_programs_compile(path: Path) -> None:
    prog = compile_source(path.read_text(), name=path.stem[:8], source=str(path))
    ops = [i.op for i in decode_program(prog.body)]
    assert ops[-1] is Op.END
    assert {Op.PMOVE, Op.GRASP, Op.RELEASE, Op.WAITI, Op.WRITEO} <= set(ops)


def test_there_are_three_transfer_examples() -> None:
    assert len(list(EXAMPLES.glob("*.aml"))) == 3


def test_aml_as_it_is_written_compiles() -> None:
    # Several statements on one line, a label and a statement together, a trailing comment.
    text = "START: PMOVE(PT(300, 100, 0, 0)); DOWN; GRASP; UP;  -- pick\nBRANCH(START); END\n"
    assert [(i.op, i.operands, i.line) for i in compile_program(text)] == [
        (Op.PMOVE, (3000, 1000, 0, 0), 1),
        (Op.DOWN, (), 1),
        (Op.GRASP, (), 1),
        (Op.UP, (), 1),
        (Op.BRANCH, (0,), 2),
        (Op.END, (), 2),
    ]


def test_speed_zmove_and_testi_encode_and_decode() -> None:
    text = "SPEED(25)\nZMOVE(-12.5)\nL: TESTI(4, 0, L); TESTI(16, 1, out)\nOUT: END\n"
    ops = compile_program(text)
    assert [(i.op, i.operands) for i in ops] == [
        (Op.SPEED, (25,)),
        (Op.ZMOVE, (-125,)),
        (Op.TESTI, (4, 0, 2)),
        (Op.TESTI, (16, 1, 4)),
        (Op.END, ()),
    ]
    records = [encode_instruction(i) for i in ops]
    assert records[0] == Record("D", bytes.fromhex("0B 19"))
    assert records[1] == Record("D", bytes.fromhex("0C FF83"))
    assert records[2] == Record("D", bytes.fromhex("0D 04 00 0002"))
    assert [(i.op, i.operands) for i in decode_program(records)] == [
        (i.op, i.operands) for i in ops
    ]


@pytest.mark.parametrize(
    ("text", "where", "message"),
    [
        ("SPEED(0)\nEND\n", "line 1, column 7", "speed \\(percent\\) 0 out of range"),
        ("SPEED(50.5)\nEND\n", "line 1, column 7", "whole number"),
        ("ZMOVE(5000)\nEND\n", "line 1, column 7", "out of range"),
        ("TESTI(3, 1)\nEND\n", "line 1, column 11", "expected ','"),
        ("TESTI(3, 1, 7)\nEND\n", "line 1, column 13", "TESTI needs a label"),
        ("TESTI(3, 1, nowhere)\nEND\n", "line 1, column 13", "undefined label NOWHERE"),
        ("GRASP; UP DOWN\nEND\n", "line 1, column 11", "separate statements with ';'"),
        ("GRASP;; UP; -- x\nEND; GRASP\n", "line 2, column 6", "statement after END"),
    ],
)
def test_new_statement_errors_say_line_and_column(text: str, where: str, message: str) -> None:
    with pytest.raises(UsageError, match=message) as info:
        compile_program(text)
    assert where in str(info.value)


@pytest.mark.parametrize(
    "record",
    [
        Record("D", b"\x0b\x00"),  # SPEED 0
        Record("D", b"\x0b\x65"),  # SPEED 101
        Record("D", b"\x0d\x03\x01\x00\x09"),  # TESTI past the end
        Record("D", b"\x0d\x00\x01\x00\x00"),  # TESTI port 0
        Record("D", b"\x0c\x00"),  # ZMOVE too short
    ],
)
def test_decode_program_refuses_bad_new_records(record: Record) -> None:
    with pytest.raises(FramingError):
        decode_program([record, encode_instruction(Instruction(Op.END))])
