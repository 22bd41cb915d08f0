"""The DNC server's shop directory, remote-request convention and diff (no link needed)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.errors import UsageError
from cellctl.kinds.iso_cnc.dnc.diff import compare
from cellctl.kinds.iso_cnc.dnc.request import Request, RequestConvention, parse_request
from cellctl.kinds.iso_cnc.dnc.store import (
    ShopStore,
    check_machine_name,
    check_program_number,
    write_new,
)
from cellctl.kinds.iso_cnc.tape import o_number, split_programs, unframe

CONVENTION = RequestConvention()


def test_received_versions_are_kept_side_by_side(tmp_path: Path) -> None:
    store = ShopStore(tmp_path)
    first = store.keep_received("mill1", 1234, b"O1234\nG0 X1\nM30\n", now=1_800_000_000)
    second = store.keep_received("mill1", 1234, b"O1234\nG0 X2\nM30\n", now=1_800_000_000)
    third = store.keep_received("mill1", 1234, b"O1234\nG0 X3\nM30\n", now=1_800_000_001)
    assert first.path.name == "O1234_20270115T080000Z.nc"
    assert second.path.name == "O1234_20270115T080000Z_2.nc"
    assert first.path.read_bytes() == b"O1234\nG0 X1\nM30\n"  # the older is untouched
    assert [k.path for k in store.received("mill1", 1234)] == [first.path, second.path, third.path]
    assert stat.S_IMODE(first.path.stat().st_mode) == 0o600
    assert stat.S_IMODE((tmp_path / "mill1").stat().st_mode) == 0o700


def test_write_new_never_replaces(tmp_path: Path) -> None:
    path = tmp_path / "O0001.nc"
    assert write_new(path, b"one")
    assert not write_new(path, b"two")
    assert path.read_bytes() == b"one"
    assert [p.name for p in tmp_path.iterdir()] == ["O0001.nc"]  # no temporary left behind


def test_programs_by_number_and_log(tmp_path: Path) -> None:
    store = ShopStore(tmp_path)
    folder = store.machine("mill1") / "programs"
    (folder / "O1234 bracket.nc").write_text("O1234\nM30\n")
    (folder / "notes.txt").write_text("not a program")
    assert store.program("mill1", 1234).name == "O1234 bracket.nc"
    assert store.resolve("mill1", "O1234") == folder / "O1234 bracket.nc"
    with pytest.raises(UsageError, match="no program O42 in"):
        store.program("mill1", 42)
    with pytest.raises(UsageError, match="not a program number"):
        store.resolve("mill1", "bracket")
    store.log("mill1", "received O1234 (10 chars)", now=1_800_000_000)
    assert store.log_lines("mill1") == ["2027-01-15T08:00:00Z received O1234 (10 chars)"]


@pytest.mark.parametrize("name", ["", ".hidden", "../up", "a/b", "x" * 65, "mill 1"])
def test_machine_names_that_cannot_be_directories(name: str) -> None:
    with pytest.raises(UsageError, match="cannot be a directory name"):
        check_machine_name(name)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("O9999 (LOAD O1234)\n", Request(1234, drip=False)),
        ("O9999(load o1234)\n", Request(1234, drip=False)),
        ("O9999\n(DRIP O77)\nM30\n", Request(77, drip=True)),
        ("O9999 (LOAD :5678 DRIP)\n", Request(5678, drip=True)),
    ],
)
def test_request_convention(text: str, expected: Request) -> None:
    assert parse_request(9999, text, CONVENTION) == expected


def test_other_programs_are_no_request() -> None:
    assert parse_request(1234, "O1234 (LOAD O5)\n", CONVENTION) is None
    off = RequestConvention(enabled=False)
    assert parse_request(9999, "O9999 (LOAD O5)\n", off) is None
    own = RequestConvention(program=8000, load="SEND", drip="DNC")
    assert parse_request(8000, "O8000 (SEND O12 DNC)\n", own) == Request(12, drip=True)


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ("O9999 (HELLO)\n", "asks for nothing"),
        ("O9999 (LOAD)\n", "must name one program"),
        ("O9999 (LOAD O1 O2)\n", "must name one program"),
        ("O9999 (LOAD O9999)\n", "names no program"),
    ],
)
def test_requests_not_understood_are_refused(text: str, said: str) -> None:
    with pytest.raises(UsageError, match=said):
        parse_request(9999, text, CONVENTION)


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=300))
def test_any_punched_request_is_a_request_or_a_refusal(text: str) -> None:
    try:
        found = parse_request(9999, text, CONVENTION)
    except UsageError as e:
        assert "O9999" in str(e)
    else:
        assert found is None or 1 <= found.program <= 99_999_999


def test_diff_ignores_framing_and_shows_what_changed() -> None:
    sent = b"\0\0%\nO1234 (PART)\nG0 X0 Y0\nG1 X10. F200\nM30\n%\0\0"
    same = b"%\r\nO1234 (PART)\r\nG0 X0 Y0\r\nG1 X10. F200\r\nM30\r\n%"
    assert compare(sent, same).same
    edited = b"%\nO1234 (PART)\nG0 X0 Y0\nG1 X12. F150\nM30\n%"
    result = compare(sent, edited, sent_name="sent", received_name="received")
    assert not result.same
    assert "-G1 X10. F200" in result.text
    assert "+G1 X12. F150" in result.text
    squeezed = b"%\nO1234(PART)\nG0X0Y0\nG1X10.F200\nM30\n%"
    assert not compare(sent, squeezed).same
    assert compare(sent, squeezed, spaces=False).same


def test_store_refuses_a_link_in_place_of_its_log(tmp_path: Path) -> None:
    store = ShopStore(tmp_path)
    target = tmp_path / "elsewhere"
    target.write_text("")
    os.symlink(target, store.machine("mill1") / "log")
    with pytest.raises(UsageError, match="cannot write the log"):
        store.log("mill1", "x")
    assert target.read_text() == ""


def test_a_lowercase_o_block_is_the_programs_number() -> None:
    data = b"%\no1003 (lower)\ng0 x1. y2.\nm30\n%\n"
    assert o_number(unframe(data)) == 1003
    assert [p.number for p in split_programs(unframe(data))] == [1003]
    check_program_number("O1003.nc", data)  # as named
    with pytest.raises(UsageError, match="its name says O1004 but its text is O1003"):
        check_program_number("O1004.nc", data)


def test_text_above_a_stray_percent_is_refused_before_a_byte_goes_out() -> None:
    data = b"O1022\nG0 X1.\n%\nG0 X5.\nM30\n%\n"
    with pytest.raises(UsageError, match=r"line 1: 'O1022' comes before the tape's opening %"):
        check_program_number("O1022.nc", data)
    with pytest.raises(UsageError, match="skips all of it as leader"):
        check_program_number("surface.nc", data)
    # A leader of NUL and blank lines, and a label after the %, are a tape's own.
    check_program_number("O1022.nc", b"\x00\x00\n \n%  label\nO1022\nM30\n%\n")
