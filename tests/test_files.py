"""Reading a file a user names: a regular file only, bounded; a device, a FIFO or a directory
in its place is refused at once (reading one would block forever or never end)."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cellctl.cell.config import check_cell
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.files import read_file, read_text
from tests.test_cell_config import cell_check, edit

pytestmark = pytest.mark.timeout(60)  # a read that blocks fails here, not at the suite's end


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    path = tmp_path / "program.aml"
    os.mkfifo(path)
    return path


def test_a_regular_file_is_read_whole(tmp_path: Path) -> None:
    path = tmp_path / "p.nc"
    path.write_bytes(b"%\nO1234\nG00 X1.\nM30\n%\n")
    assert read_file(path) == b"%\nO1234\nG00 X1.\nM30\n%\n"
    assert read_text(path, "ascii") == "%\nO1234\nG00 X1.\nM30\n%\n"
    path.write_bytes(b"G00 X1.\xff\n")
    with pytest.raises(UnicodeDecodeError):
        read_text(path, "ascii")
    assert read_text(path, "ascii", "replace") == "G00 X1.\ufffd\n"


@pytest.mark.parametrize(
    ("make", "said"),
    [
        ("fifo", "a FIFO, not a regular file"),
        ("device", "a character device, not a regular file"),
        ("directory", "a directory, not a regular file"),
    ],
)
def test_what_is_not_a_file_is_refused_before_it_is_read(
    tmp_path: Path, make: str, said: str
) -> None:
    if make == "fifo":
        path = tmp_path / "fifo"
        os.mkfifo(path)  # no writer: an open for reading would wait for one
    elif make == "device":
        path = Path("/dev/zero")  # endless
    else:
        path = tmp_path
    with pytest.raises(OSError) as caught:
        read_file(path)
    assert (caught.value.errno, caught.value.strerror) == (errno.EINVAL, said)
    assert caught.value.filename == str(path)


def test_a_file_over_the_limit_is_refused_whole(tmp_path: Path) -> None:
    path = tmp_path / "big.nc"
    path.write_bytes(b"G01 X1. F100\n" * 100)
    assert len(read_file(path, limit=1300)) == 1300
    with pytest.raises(OSError) as caught:
        read_file(path, limit=1299)
    assert caught.value.errno == errno.EFBIG
    assert caught.value.strerror == "more than 1299 bytes (refused whole)"
    with pytest.raises(FileNotFoundError):
        read_file(tmp_path / "missing.nc")


def test_a_cell_whose_programs_name_a_device_or_a_fifo_is_checked_at_once(
    tmp_path: Path, fifo: Path
) -> None:
    """A device's path under the wrong table (the robot's link under [robot_programs]) and a
    FIFO as a route's program: each is a problem, and the check ends."""
    directory = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    edit(directory, '"robot/cnc1_to_cnc2.aml"', '"/dev/zero"')
    edit(directory, '"programs/robot_base_rough_cnc1.dyn"', f'"{fifo}"')
    config, problems = check_cell(directory)
    assert config is None
    assert any(
        p.startswith("[robot_programs] cnc1_to_cnc2: /dev/zero:")
        and "a character device, not a regular file" in p
        for p in problems
    ), problems
    assert any(str(fifo) in p and "a FIFO, not a regular file" in p for p in problems), problems
    code, out = cell_check(directory)
    assert code != 0 and "a FIFO, not a regular file" in out


def test_a_program_sent_by_hand_that_is_a_fifo_is_refused_before_a_byte_goes_out(
    fifo: Path,
) -> None:
    """A mill's download by hand reads its program through the same check: the command ends
    with the refusal (no controller, no emulator: nothing else is asked)."""
    result = subprocess.run(
        [sys.executable, "-m", "cellctl", "mill", "--link", "mem://nobody", "download", str(fifo)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode != 0
    assert "a FIFO, not a regular file" in result.stderr + result.stdout, result


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["emulate", "iso-cnc", "--load", "{fifo}"], "--load {fifo}: cannot read it: a FIFO"),
        (["emulate", "ur", "--program", "tend.urp={fifo}"], "{fifo}: cannot read it: a FIFO"),
    ],
)
def test_an_emulator_given_a_fifo_to_load_says_so_and_exits_2(
    fifo: Path, args: list[str], said: str
) -> None:
    """In the user's words, before anything is served (no ``[Errno 22]``, no traceback)."""
    result = subprocess.run(
        [sys.executable, "-m", "cellctl", *(a.format(fifo=fifo) for a in args)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 2, result
    assert result.stderr.strip().startswith(f"error: {said.format(fifo=fifo)}"), result.stderr
    assert "Traceback" not in result.stderr and "Errno" not in result.stderr


def test_a_program_that_is_not_ascii_is_refused_with_its_byte(tmp_path: Path) -> None:
    program = tmp_path / "O1.nc"
    program.write_bytes(b"O1\n\xff\nM30\n")
    result = subprocess.run(
        [sys.executable, "-m", "cellctl", "emulate", "iso-cnc", "--load", str(program)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert (result.returncode, result.stderr.strip()) == (
        2,
        f"error: --load {program}: cannot read it: byte 4 is not ascii text",
    )
