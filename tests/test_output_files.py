"""A file named for output (a drawing, a compiled program, a report) is written, or replaced,
but never through a symbolic link: a link planted where the output goes would turn the write
onto another file. Refused with exit 2 and the link named, the file behind it untouched."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from cellctl.ui.cli import main

ROOT = Path(__file__).resolve().parent.parent
PROGRAM = ROOT / "examples" / "programs" / "robot_base_rough_cnc1.dyn"
AML = ROOT / "examples" / "robot" / "conveyor_to_cnc1.aml"


def cellctl(*args: str) -> Result:
    return CliRunner().invoke(main, list(args))


def _preview(out: Path, _tmp: Path) -> Result:
    return cellctl("program", "preview", str(PROGRAM), "-o", str(out))


def _mill_preview(out: Path, _tmp: Path) -> Result:
    return cellctl("mill", "preview", str(PROGRAM), "-o", str(out))


def _compile(out: Path, _tmp: Path) -> Result:
    return cellctl("robot", "compile", str(AML), "-o", str(out))


def _report(out: Path, tmp: Path) -> Result:
    cell = tmp / "cell"
    if not cell.exists():
        shutil.copytree(ROOT / "examples" / "cell", cell)
    return cellctl("--cell", str(cell), "report", "shift", "--csv", str(out))


WRITERS: dict[str, tuple[Callable[[Path, Path], Result], str]] = {
    "program preview": (_preview, "drawing.svg"),
    "mill preview": (_mill_preview, "drawing.svg"),
    "robot compile": (_compile, "program.rec"),
    "report shift --csv": (_report, "shift.csv"),
}


@pytest.mark.parametrize("command", list(WRITERS))
def test_output_goes_to_the_file_never_through_a_link(tmp_path: Path, command: str) -> None:
    write, name = WRITERS[command]
    out = tmp_path / name
    written = write(out, tmp_path)
    assert written.exit_code == 0, written.output
    assert out.stat().st_size > 0 and not out.is_symlink()
    # Written again over itself: replaced.
    assert write(out, tmp_path).exit_code == 0
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me\n")
    out.unlink()
    out.symlink_to(victim)
    refused = write(out, tmp_path)
    assert refused.exit_code == 2, refused.output
    said = " ".join(refused.output.split())
    assert f"{out}: cannot write: a symbolic link" in said, said
    assert victim.read_text() == "keep me\n"
