"""Property tests of everything a user hands cellctl as text: only CellctlError subclasses come
out, valid inputs round-trip, nothing hangs (hypothesis deadlines, pytest-timeout).

Robot records and `.rec` files, the AML/E compiler, the DYNALAN parser, validator and splitter,
the PLC map, link URLs and line settings. Examples that found bugs are kept as ``@example``.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

from hypothesis import example, given, settings
from hypothesis import strategies as st

from cellctl.errors import CellctlError
from cellctl.kinds.dyna2400 import dynalan
from cellctl.kinds.ibm7545.aml import compile_program, compile_source, decode_program
from cellctl.kinds.ibm7545.records import ProgramFile, Record, decode_record, encode_record
from cellctl.link import LineSettings, parse_host_port
from cellctl.protocol.plc import PlcMap

FAST = settings(max_examples=60, deadline=2000)

_AML_WORDS = st.sampled_from(
    [
        "PMOVE(PT(500, -300, 0, 0))",
        "PMOVE(PT(1.5, 2, 3, 400))",
        "DOWN",
        "UP",
        "GRASP",
        "RELEASE",
        "SPEED(50)",
        "SPEED(0)",
        "ZMOVE(12.5)",
        "TESTI(3, 1, A)",
        "TESTI(3, 1, 7)",
        "WAITI(1, 1)",
        "WRITEO(17, 0)",
        "DELAY(1.5)",
        "BRANCH(A)",
        "A:",
        "A: A:",
        "END",
        ";",
        "-- note",
        "(",
        "9" * 60,
        "é",
    ]
)

_DYN_ROWS = st.sampled_from(
    [
        "START INS 01",
        "START MM 01",
        "GO X 1.000",
        "GR Y -.5",
        "GR A 90",
        "ZERO AT",
        "  X 1",
        "FR XYZ = 0",
        "FR XY = 8",
        "TD = 0",
        "TD = .125",
        "CPOCKET R= .750 ZD= -.800 DP= 0.0000001",
        "CPOCKET R= .5 ZD= -.2 DP= .1",
        "RPOCKET XL= 1 YL= 1 ZD= -.1",
        "ARCFRAME R= 1 A= 360 ZD= -.1 DP= .05",
        "DRIL PECK= .0000001",
        "ZH= 0",
        "ZD= -1",
        "REPEAT 99",
        "REPEAT END",
        "SKIP TO 003",
        "SKIP TO 900",
        "DWELL 1",
        "HALT",
        "; A COMMENT",
        "GO X " + "9" * 40,
        "",
    ]
)


@st.composite
def dynalan_texts(draw: st.DrawFn) -> str:
    rows = draw(st.lists(_DYN_ROWS, max_size=40))
    numbers = draw(st.lists(st.integers(0, 999), min_size=len(rows), max_size=len(rows)))
    sequential = draw(st.booleans())
    lines = [
        f"{(i if sequential else n):03d} {row}".rstrip()
        for i, (row, n) in enumerate(zip(rows, numbers, strict=True))
    ]
    if draw(st.booleans()):
        lines += [f"{len(lines):03d} SKIP TO 900", "900"]
    return "\n".join(lines) + "\n"


# -- robot records and .rec files ----------------------------------------------------------------


@FAST
@given(ident=st.sampled_from("NDE"), data=st.binary(max_size=40))
def test_record_round_trips(ident: str, data: bytes) -> None:
    record = Record(ident, data)
    wire = encode_record(record)
    assert decode_record(wire) == (record, len(wire))


@FAST
@given(st.binary(max_size=80))
def test_record_decoder_answers_anything(data: bytes) -> None:
    try:
        _, used = decode_record(data)
    except CellctlError:
        return
    assert 0 <= used <= len(data)


@FAST
@given(st.text(max_size=300))
@example("N09015846455231202020C7\nD010A0A\nE0000\n")
@example("N0901\x00\nE0000")
def test_rec_parser_answers_anything(text: str) -> None:
    with contextlib.suppress(CellctlError):
        ProgramFile.parse(text)


@FAST
@given(st.binary(max_size=200))
def test_rec_loader_answers_any_bytes(data: bytes) -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "p.rec"
        path.write_bytes(data)
        with contextlib.suppress(CellctlError):
            ProgramFile.load(path)


# -- AML/E ---------------------------------------------------------------------------------------


@FAST
@given(st.lists(st.lists(_AML_WORDS, max_size=4), max_size=12))
@example([["START:", "PMOVE(PT(300, 100, 0, 0))", ";", "DOWN", ";", "GRASP", ";", "UP", ";"]])
def test_aml_compiler_answers_anything_and_valid_programs_round_trip(
    rows: list[list[str]],
) -> None:
    text = "\n".join(" ".join(row) for row in rows) + "\n"
    try:
        instructions = compile_program(text)
    except CellctlError:
        return
    program = compile_source(text, "PROP", 1)
    again = decode_program(ProgramFile.parse(program.to_text()).body)
    assert [(i.op, i.operands) for i in again] == [(i.op, i.operands) for i in instructions]


@FAST
@given(st.text(max_size=200))
def test_aml_compiler_answers_any_text(text: str) -> None:
    with contextlib.suppress(CellctlError):
        compile_program(text)


# -- DYNALAN ---------------------------------------------------------------------------------------


@settings(max_examples=80, deadline=5000)
@given(dynalan_texts())
@example("000 START INS 01\n001 FR XYZ = 0\n002 GR X 1.0\n003 SKIP TO 900\n900\n")
@example("000 GO Z -.1\n001 CPOCKET R= .750 ZD= -.800 DP= 0.0000001\n002 SKIP TO 900\n900\n")
def test_dynalan_validator_answers_and_valid_programs_split_and_join(text: str) -> None:
    program = dynalan.parse_program(text)
    result = dynalan.validate(program)
    for problem in result.problems:
        assert problem.row >= 1 and problem.column >= 1
    if not program.ok:
        return
    try:
        blocks = dynalan.split_program(program)
    except CellctlError:
        return
    joined = dynalan.join_blocks(blocks)
    again = dynalan.split_program(dynalan.parse_program(joined))
    assert [b.text() for b in again] == [b.text() for b in blocks]


@FAST
@given(st.text(max_size=300))
def test_dynalan_parser_answers_any_text(text: str) -> None:
    result = dynalan.validate(dynalan.parse_program(text))
    assert all(p.row >= 1 for p in result.problems)


@FAST
@given(st.binary(max_size=80))
def test_dynalan_line_decoder_uses_what_it_says(data: bytes) -> None:
    used, _ = dynalan.decode_line(data)
    assert 0 <= used <= len(data)


# -- PLC map, link URLs and line settings --------------------------------------------------------

_ANY = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=10)),
    lambda inner: st.one_of(
        st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=8), inner, max_size=3)
    ),
    max_leaves=8,
)


@FAST
@given(
    st.dictionaries(
        st.sampled_from(["url", "unit", "timeout", "poll", "coils", "inputs", "other"]),
        _ANY,
        max_size=4,
    )
)
@example({"url": "modbus://127.0.0.1:502", "coils": {"go_1": 70000}})
@example({"timeout": float("nan")})
def test_plc_map_answers_anything(table: dict[str, Any]) -> None:
    with contextlib.suppress(CellctlError):
        PlcMap.from_toml(table)


@FAST
@given(st.text(max_size=40))
@example("socket://host:99999")
@example("rfc2217://[::1]:7001")
def test_parse_host_port_answers_anything(url: str) -> None:
    try:
        host, port = parse_host_port(url)
    except CellctlError:
        return
    assert host and 0 <= port <= 65535


@FAST
@given(st.text(max_size=30))
@example("4800,7E2")
@example("9600,8N1,rtscts")
def test_line_settings_answer_anything(text: str) -> None:
    with contextlib.suppress(CellctlError):
        LineSettings.parse(text)
