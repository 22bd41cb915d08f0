"""The iso-cnc codecs: ISO tape framing, the G-code check, the motion model (no I/O)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.errors import UsageError
from cellctl.kinds import registry
from cellctl.kinds.iso_cnc import gcode, motion, tape
from cellctl.kinds.iso_cnc.gcode import CheckOptions
from cellctl.kinds.kind import ProgramRole

ISO_TEXT = st.text(
    alphabet=st.sampled_from("OGXYZIJKFMNRS0123456789.- ()\n"), min_size=0, max_size=400
)


def messages(text: str, **options: object) -> list[str]:
    return [f.format("p.nc") for f in gcode.check(text, CheckOptions(**options))]  # type: ignore[arg-type]


# -- tape --------------------------------------------------------------------------------------


def test_the_control_codes_are_the_spec_s_table() -> None:
    assert [(c.name, int(c)) for c in tape.CONTROL_CODES] == [
        ("DC1", 0x11),
        ("DC2", 0x12),
        ("DC3", 0x13),
        ("DC4", 0x14),
    ]
    assert tape.control_code_name(0x13) == "DC3" and tape.control_code_name(0x41) == "0x41"


def test_a_tape_is_leader_percent_blocks_percent_trailer() -> None:
    data = tape.frame("O1234 (PART)\nG0 X0\nM30\n", leader=3, trailer=2, percent=True)
    assert data == b"\0\0\0%\nO1234 (PART)\nG0 X0\nM30\n%\0\0"
    # a file that carries its own % lines is not framed twice; CR goes
    assert tape.frame("%\r\nO1234\r\nM30\r\n%\r\n", leader=0, trailer=0) == b"%\nO1234\nM30\n%"
    assert tape.frame("O1\nM30", leader=0, trailer=0, percent=False) == b"O1\nM30\n"


def test_unframe_skips_leader_label_and_trailer() -> None:
    assert tape.unframe(b"\0\0%LABEL SKIPPED\nO1\r\nM30\n%\0\0") == "O1\nM30\n"
    assert tape.unframe(b"O1\nM30") == "O1\nM30\n"
    assert tape.unframe(b"\0\0%") == ""


def test_split_programs_by_o_number_with_titles() -> None:
    found = tape.split_programs("O1 (FIRST)\nG0 X1\nM30\n:0002\nM30\n")
    assert [(p.number, p.title) for p in found] == [(1, "FIRST"), (2, "")]
    assert found[0].text == "O1 (FIRST)\nG0 X1\nM30\n"
    assert tape.o_number("\n%\nO0042 (X)\nM30\n") == 42
    assert tape.o_number("G0 X1\n") is None


def test_a_character_a_tape_cannot_carry_is_refused() -> None:
    with pytest.raises(UsageError, match="line 2"):
        tape.frame("O1\nG0 X1 \u00e9\n", leader=0, trailer=0)


def test_alarm_reports_parse_whole_or_ask_for_more() -> None:
    assert tape.parse_alarm(tape.alarm_report(87)) == (87, 5)
    assert tape.parse_alarm(b"\x1508") is None
    assert tape.parse_alarm(b"\x15xyzzy") == (0, 1)
    assert tape.ALARMS[85] == "COMMUNICATION ERROR" and tape.ALARMS[86] == "DR OFF"


@given(ISO_TEXT, st.integers(0, 30), st.integers(0, 30))
def test_framing_then_unframing_gives_the_program_back(text: str, lead: int, trail: int) -> None:
    body = tape.body_text(text.replace("%", ""))
    assert tape.unframe(tape.frame(body, leader=lead, trailer=trail)) == body


@given(st.binary(max_size=600))
def test_any_bytes_unframe_and_split_without_error(data: bytes) -> None:
    text = tape.unframe(data)
    programs = tape.split_programs(text)
    # nothing is lost but blank lines before the first program
    assert "".join(p.text for p in programs).strip() == text.strip()
    assert all(p.number >= 0 for p in programs)


# -- the G-code check --------------------------------------------------------------------------


GOOD = """%
O1234 (BRACKET)
G21 G90 G17 G40 G49 G80
T1 M6
G0 X0 Y0 S3000 M3
G43 H1 Z5
G1 Z-1 F200
G1 X20
G2 X30 Y10 I0 J10
G3 X20 Y20 R10
G4 P500
G81 X5 Y5 Z-3 R1 F100
G80 G0 Z50
M30
%
"""


def test_a_good_program_has_no_problem() -> None:
    assert messages(GOOD) == []


@pytest.mark.parametrize(
    ("block", "expected"),
    [
        ("G0 G1 X1 F100", "p.nc:3:4: G0 and G1 in one block (group 1)"),
        ("G90 G91 X1", "p.nc:3:5: G90 and G91 in one block (group 3)"),
        ("M3 M5", "p.nc:3:4: M3 and M5 in one block (spindle)"),
        ("G1 X1 X2 F10", "p.nc:3:7: X twice in one block"),
        ("G7 X1", "p.nc:3:1: G7: no such G code"),
        ("S123456", "p.nc:3:1: S123456: spindle speed, rpm out of range 0 to 99999"),
        ("T1.5", "p.nc:3:1: T1.5: tool number must be whole"),
        ("G1 X1 (open", "p.nc:3:7: comment not closed in its block"),
        ("G1 X1 (a (b) F1", "p.nc:3:10: ( inside a comment (they do not nest)"),
        ("G1 X1 F1 $", "p.nc:3:10: '$' is not part of a word"),
        ("G1 X F1", "p.nc:3:4: X without a number"),
        ("G1 X10", "p.nc:3: G01 move with no feed: no F before it"),
        ("G2 X10 Y0 F100", "p.nc:3: G02 without I/J/K or R"),
        ("G2 X10 Y0 R5 I5 F100", "p.nc:3: G02 with both R and I/J/K"),
    ],
)
def test_each_problem_is_named_at_its_line_and_column(block: str, expected: str) -> None:
    assert expected in messages(f"O1\nG90 G0 X0 Y0\n{block}\nM30\n")


def test_arcs_are_checked_for_radius_agreement_and_chord() -> None:
    text = "O1\nG90 G0 X0 Y0\nG2 X10 Y0 I5.1 J0 F100\nG2 X0 Y0 R4\nM30\n"
    found = messages(text)
    assert any("p.nc:3: G02: start radius 5.1000 and end radius 4.9000" in m for m in found)
    assert any("p.nc:4:10: G02: R4 is shorter than half the chord (5.000 mm)" in m for m in found)
    assert messages(text, arc_tolerance_mm=0.5) == [
        m for m in found if "radius" not in m or "start" not in m
    ]


def test_o_number_and_percent_framing() -> None:
    assert "p.nc:1:1: no O-number: the program's first block must be O and its number" in (
        messages("G0 X1\nM30\n")
    )
    assert messages("O12345\nM30\n") == [
        "p.nc:1:1: O12345: more than 4 digits (this control's programs are O1 to O9999)"
    ]
    assert messages("O12345\nM30\n", o_digits=8) == []
    assert messages("%\nO1\nM30\n%\nG0 X1\n") == [
        "p.nc:5:1: text after the closing %: a control never reads it"
    ]
    assert "p.nc:1:1: warning: % not closed: the tape has no ending %" in messages("%\nO1\nM30\n")


@given(ISO_TEXT)
@settings(max_examples=200)
def test_any_text_checks_to_findings_with_lines_and_columns(text: str) -> None:
    lines = text.count("\n") + 1
    for f in gcode.check(text):
        assert 1 <= f.line <= lines and f.column >= 0 and f.message


@given(st.binary(max_size=400))
def test_any_bytes_check_without_error(data: bytes) -> None:
    found = gcode.check(data.decode("latin-1"), CheckOptions(max_findings=20))
    assert len(found) <= 21


# -- the motion model --------------------------------------------------------------------------


def seconds(text: str, **model: float) -> list[float]:
    return motion.block_seconds(gcode.blocks(text), motion.MotionModel(**model))


def test_feed_moves_take_their_length_at_f() -> None:
    got = seconds("G21 G90 G0 X0 Y0\nG1 X60 F600\nG91 G1 X30 Y40\n")
    assert got[1] == pytest.approx(6.0) and got[2] == pytest.approx(5.0)


def test_rapids_take_the_longest_axis_at_the_rapid_rate() -> None:
    got = seconds("G90 G0 X100 Y50\n", rapid_mm_min=6000)
    assert got == [pytest.approx(1.0)]


def test_arcs_by_their_length_and_dwell_by_p() -> None:
    got = seconds("G90 G0 X60 Y0\nG2 X70 Y10 R10 F600\nG3 X60 Y0 I-10 J0\nG4 P500\n")
    assert got[1] == pytest.approx(math.pi * 10 / 2 / 10)
    assert got[2] == pytest.approx(math.pi * 10 * 1.5 / 10)
    assert got[3] == pytest.approx(0.5)


def test_inch_programs_and_acceleration() -> None:
    assert seconds("G20 G90 G1 X1 F60\n")[0] == pytest.approx(1.0)
    accel = seconds("G21 G90 G1 X1 F6000\n", accel_mm_s2=1000)
    assert accel[0] == pytest.approx(2 * math.sqrt(1 / 1000))


@given(ISO_TEXT)
def test_any_program_has_finite_non_negative_block_times(text: str) -> None:
    for s in seconds(text):
        assert s >= 0 and math.isfinite(s)


# -- the kind's language hooks -----------------------------------------------------------------


def test_the_kind_checks_times_and_previews_a_program(tmp_path: Path) -> None:
    kind = registry.kind("iso-cnc")
    assert kind.language is not None and kind.language.preview is not None
    options = kind.checked_options({})
    path = tmp_path / "O1234.nc"
    path.write_text(GOOD, encoding="ascii")
    checked = kind.language.check(path, ProgramRole.MILLING, options)
    assert checked.ok and checked.lines == len(gcode.blocks(GOOD))
    assert checked.machining_s == pytest.approx(motion.program_seconds(gcode.blocks(GOOD)))
    preview = kind.language.preview(GOOD, "O1234.nc", options)
    assert preview.svg.count("<polyline") >= 2 and preview.blocks == checked.lines
    path.write_text("O1\nG0 G1 X1 F100\nM30\n", encoding="ascii")
    bad = kind.language.check(path, ProgramRole.MILLING, options)
    assert bad.problems == (f"{path}:2:4: G0 and G1 in one block (group 1)",)
    assert kind.check_text is not None
    assert kind.check_text("run", "p.nc", "G1 X1\n", options)[0].startswith("p.nc:1")
    with pytest.raises(UsageError, match="unknown option"):
        kind.checked_options({"dc3_tolerence": 10})


def test_a_tape_cut_short_ends_with_its_block_and_percent() -> None:
    """How a host ends a tape early (spec: % ends a transmission): the rest of the block
    in flight, then %; whole blocks only reach the control, and it reads a closed tape."""
    from cellctl.kinds.iso_cnc.tape import cut_tape, frame, unframe

    text = "O1234\nG00 X0\nG01 X10. F300\nM30\n"
    tape = frame(text, leader=3, trailer=3)
    mid = tape.index(b"X10.")  # in the middle of the third block
    cut = cut_tape(tape, mid)
    assert cut == tape[: tape.index(b"F300\n") + 5] + b"%"
    assert unframe(cut) == "O1234\nG00 X0\nG01 X10. F300\n"
    at_boundary = tape.index(b"G01")
    assert cut_tape(tape, at_boundary) == tape[:at_boundary] + b"%"
    assert cut_tape(tape, 0) == b"\0\0\0%\n%"  # nothing of a program yet: an empty tape
    assert cut_tape(tape, tape.index(b"M30") + 1) is None  # its end is in the block in flight
    plain = frame(text, percent=False)
    assert cut_tape(plain, plain.index(b"X0"), percent=False) == b"O1234\nG00 X0\nM30\n"
