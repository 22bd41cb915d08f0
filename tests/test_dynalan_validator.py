"""Validator: every problem with line number, column and a plain message; the broken samples."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.kinds.dyna2400.dynalan import (
    ProgramRole,
    Severity,
    Travel,
    Units,
    ValidationContext,
    parse_program,
    validate,
)
from cellctl.kinds.dyna2400.dynalan.machine import MachineConfig

PROGRAMS = Path(__file__).resolve().parent.parent / "examples" / "programs"


def _expected() -> list[tuple[str, int, int, str]]:
    rows = []
    for text in (PROGRAMS / "broken" / "expected.txt").read_text().splitlines():
        if text.startswith("#") or not text.strip():
            continue
        name, where, code = text.split()
        row, column = (int(x) for x in where.split(":"))
        rows.append((name, row, column, code))
    return rows


@pytest.mark.parametrize(("name", "row", "column", "code"), _expected())
def test_each_broken_sample_gives_its_error(name: str, row: int, column: int, code: str) -> None:
    program = parse_program((PROGRAMS / "broken" / name).read_text(), name=name)
    result = validate(program)
    assert not result.ok
    first = result.errors[0]
    assert (first.row, first.column, first.code) == (row, column, code), first.format(name)
    assert first.message
    assert result.blocks is None


def test_every_broken_sample_is_listed() -> None:
    listed = {row[0] for row in _expected()}
    on_disk = {p.name for p in (PROGRAMS / "broken").glob("*.dyn")}
    assert on_disk - listed == {"setup_mm.dyn"}


@pytest.mark.parametrize("path", sorted(PROGRAMS.glob("*.dyn")), ids=lambda p: p.name)
def test_good_samples_validate_without_errors(path: Path) -> None:
    result = validate(parse_program(path.read_text(), name=path.name))
    assert result.errors == []


def test_mm_setup_against_an_inch_machine_is_a_units_mixup() -> None:
    text = (PROGRAMS / "broken" / "setup_mm.dyn").read_text()
    result = validate(parse_program(text), ValidationContext(units=Units.INS))
    assert [p.code for p in result.errors] == ["units-mix"]
    assert "MM" in result.errors[0].message and "INS" in result.errors[0].message


def test_feed_limits_scale_for_metric_programs() -> None:
    ok = "000 START MM 01\n001 FR XYZ = 800.0\n002 SETUP >zcxyu\n003 SKIP TO 900\n900\n"
    assert validate(parse_program(ok)).ok
    slow = ok.replace("800.0", "2.0")
    result = validate(parse_program(slow))
    assert result.errors[0].code == "feed-range"
    assert "mm/min" in result.errors[0].message


def test_all_problems_are_reported_not_just_the_first() -> None:
    text = (
        "000 GO X 1.000\n"
        "001   Y 1.0 Z 1\n"
        "002 FR XYZ = 99\n"
        "003 FOO\n"
        "004 SKIP TO 070\n"
        "005 GR X 1.2.3\n"
        "006 SKIP TO 900\n"
        "900\n"
    )
    result = validate(parse_program(text))
    assert [p.code for p in result.errors] == [
        "continuation",
        "feed-range",
        "unknown-statement",
        "skip",
        "bad-number",
    ]
    assert [p.number for p in result.errors] == ["001", "002", "003", "004", "005"]


def test_warnings_are_separate_from_errors() -> None:
    text = "000 GO X 1.00001\n001 END\n"
    result = validate(parse_program(text), ValidationContext(role=ProgramRole.MILLING))
    assert result.ok
    assert {p.code for p in result.warnings} >= {"precision", "end", "unclosed-block"}
    assert all(p.severity is Severity.WARNING for p in result.warnings)


def test_travel_is_configurable_per_machine() -> None:
    text = "000 GO X 9.000\n001 SKIP TO 900\n900\n"
    assert not validate(parse_program(text)).ok
    wide = ValidationContext(config=MachineConfig(travel=Travel(x_max=12.0)))
    assert validate(parse_program(text), wide).ok


def test_moves_inside_a_repeat_are_checked_on_every_pass() -> None:
    text = "000 REPEAT 10\n001 GR X 1.000\n002 REPEAT END\n003 SKIP TO 900\n900\n"
    result = validate(parse_program(text))
    assert [(p.code, p.number) for p in result.errors] == [("travel", "001")]


def test_skip_backwards_and_into_a_repeat_are_errors() -> None:
    back = "000 GO X 1.000\n001 SKIP TO 000\n002 SKIP TO 900\n900\n"
    assert "backwards" in validate(parse_program(back)).errors[0].message
    into = "000 SKIP TO 002\n001 REPEAT 02\n002 GR X .1\n003 REPEAT END\n004 SKIP TO 900\n900\n"
    assert "REPEAT" in validate(parse_program(into)).errors[0].message


def test_start_must_be_line_000() -> None:
    text = "000 TD = .125\n001 START INS 01\n002 SETUP >zcxyu\n003 SKIP TO 900\n900\n"
    assert validate(parse_program(text)).errors[0].code == "start"


def test_multi_block_files_name_the_block() -> None:
    good = "000 GO X 1.000\n001 SKIP TO 900\n900\n"
    bad = "000 GO X 1.000\n001 FR XY = 50\n002 SKIP TO 900\n900\n"
    result = validate(parse_program(good + bad))
    problem = result.errors[0]
    assert problem.block == 2 and problem.where() == "block 2 line 001"
    assert problem.format("P.DYN").startswith("P.DYN:5:13: error [feed-range] block 2 line 001")


def test_empty_program_is_an_error() -> None:
    assert validate(parse_program("\n\n")).errors[0].code == "empty"
