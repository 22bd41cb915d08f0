"""What ``cellctl dnc check|send|drip`` and ``cellctl program check`` say of what they cannot
check whole: a program with more problems than the check lists (how many were found, and
that checking stopped), and a path that is no regular file (what it is). Through the real
command line; the G-code check's own bounds on its own."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.errors import UsageError
from cellctl.kinds.iso_cnc import gcode
from cellctl.kinds.iso_cnc.options import IsoCncOptions, prepare
from cellctl.ui.cli import main

from .conftest import CELLCTL

#: Three problems a line (numbers that must be whole), 200 lines: checking stops at line 35.
FLOOD = "O1\n" + "D1.5 H1.5 L1.5\n" * 200 + "M30\n"


@pytest.fixture
def shop(tmp_path: Path) -> Path:
    root = tmp_path / "shop"
    root.mkdir()
    (root / "dnc.toml").write_text('[machines.mill1]\nlink = "rfc2217://192.0.2.10:4001"\n')
    return root


def dnc(shop: Path, *args: str) -> tuple[int, str]:
    result = CliRunner().invoke(main, ["dnc", *args, "--dir", str(shop)])
    return result.exit_code, " ".join(result.output.split())


def test_the_check_stops_at_its_limit_and_counts_what_it_found() -> None:
    found = gcode.check(FLOOD)
    *listed, note = found
    assert len(listed) == 100 and all(f.unlisted is None for f in listed)
    assert (note.line, note.unlisted) == (35, 2)  # 34 lines of 3: 102 found, 100 listed
    assert note.message == "checking stopped here: 2 more problems found, not listed"
    assert gcode.counted(found) == (
        "102 problems found before checking stopped at line 35 (the first 100 listed)"
    )
    # The program's end was not reached: nothing is said of it (it does end with M30).
    assert not any("M30" in f.message for f in found)
    # Not checked to its end: never sent (the note is one of the errors).
    assert gcode.errors(FLOOD)[-1] == note
    with pytest.raises(UsageError):
        prepare(FLOOD.encode(), IsoCncOptions())
    assert gcode.counted(gcode.errors("O1\nU\nM30\n")) == "1 problem(s)"
    # One problem a block where a block goes wrong: the rest of it is not read as words.
    assert gcode.counted(gcode.errors("O1\nU S Q\nM30\n")) == "1 problem(s)"


def test_lines_too_long_to_check_stop_the_check_too() -> None:
    text = "O1\n" + ("X" * 300 + "\n") * 1000 + "M30\n"
    found = gcode.check(text, gcode.CheckOptions(max_findings=20))
    # stopped at the 21st line too long, the one past the limit: the 979 after it unread
    assert len(found) == 21 and (found[-1].line, found[-1].unlisted) == (22, 1), found[-1]


def test_dnc_check_counts_the_problems_found_not_its_note(shop: Path, tmp_path: Path) -> None:
    flood = tmp_path / "O0001.nc"
    flood.write_text(FLOOD)
    code, said = dnc(shop, "check", "mill1", str(flood))
    assert code == 1, said
    assert f"{flood}:35: checking stopped here: 2 more problems found, not listed" in said
    assert (
        f"{flood}: 102 problems found before checking stopped at line 35 (the first 100 "
        "listed): cellctl refuses to send it to mill1"
    ) in said
    assert "101 problem" not in said


def test_program_check_counts_the_problems_found_not_its_note(tmp_path: Path) -> None:
    """`cellctl program check` of the same program counts as `dnc check` does."""
    flood = tmp_path / "O0001.nc"
    flood.write_text(FLOOD)
    result = CliRunner().invoke(main, ["program", "check", "--kind", "iso-cnc", str(flood)])
    said = " ".join(result.output.split())
    assert result.exit_code == 1, said
    assert (
        f"{flood}: 102 problems found before checking stopped at line 35 (the first 100 "
        "listed) as an iso-cnc program"
    ) in said
    assert "101 problem" not in said


def not_regular(path: str) -> str:
    """What every reader of a file says of ``path`` (cellctl.files)."""
    what = "a directory" if Path(path).is_dir() else "a character device"
    return f"{path}: {what}, not a regular file"


@pytest.mark.parametrize("path", ["/dev/zero", "DIR"])
def test_a_path_that_is_no_regular_file_is_said_to_be_what_it_is(
    shop: Path, tmp_path: Path, path: str
) -> None:
    path = str(tmp_path) if path == "DIR" else path
    for command in ("check", "send", "drip"):
        code, said = dnc(shop, command, "mill1", path)
        assert code == 2, said
        assert not_regular(path) in said, said
        assert "no such file" not in said
    # `program check` and `program preview` say it in the same words (one place: cellctl.files)
    for args in (["check", "--kind", "iso-cnc", path], ["preview", path, "-o", "x.svg"]):
        result = CliRunner().invoke(main, ["program", *args])
        assert result.exit_code == 2
        assert not_regular(path) in " ".join(result.output.split())


def test_a_missing_file_and_an_o_number_are_said_as_before(shop: Path, tmp_path: Path) -> None:
    code, said = dnc(shop, "check", "mill1", str(tmp_path / "gone.nc"))
    assert code == 2 and "gone.nc: no such file, and not a program number like O1234" in said
    # A directory named like an O-number is not what `1234` means: the program O1234 is.
    os.mkdir(tmp_path / "1234")
    done = subprocess.run(
        [*CELLCTL, "dnc", "check", "mill1", "1234", "--dir", str(shop)],
        cwd=tmp_path, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 2
    assert re.search(r"no program O1234 in .*mill1/programs", done.stderr), done.stderr
