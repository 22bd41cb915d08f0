"""`cellctl --cell DIR emulate cell` next to a real cell: refused before a file is touched.

A cell.toml that `emulate cell` did not write (no "# Emulated cell (time scale ...)" first
line) is a cell's own configuration; emulating in its directory would replace it, and the
programs beside it, by the template's. A directory the emulation wrote before is its own:
emulated again, as the demo, the docs and the tests do."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from cellctl.emulators.cell import EXAMPLE_CELL, EmulatedCell

from .conftest import CELLCTL

PLUGIN_CELL = Path(__file__).resolve().parent / "plugins" / "kerf_cell"


def _files(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory`` and its bytes; links as their target's name."""
    out: dict[str, bytes] = {}
    for path in sorted(directory.rglob("*")):
        name = str(path.relative_to(directory))
        if path.is_symlink():
            out[name] = str(path.readlink()).encode()
        elif path.is_file():
            out[name] = path.read_bytes()
    return out


def _real_cell(source: Path, directory: Path) -> Path:
    """A real cell's directory: ``source`` copied, one robot program edited as its owner
    would (so that a copy of the template over it would show)."""
    shutil.copytree(source, directory)
    program = next(iter(sorted((directory / "robot").glob("*.aml"))))
    program.write_text(program.read_text() + "-- edited in this cell\n")
    return directory


@pytest.mark.parametrize("source", [EXAMPLE_CELL, PLUGIN_CELL], ids=["example", "saw"])
@pytest.mark.parametrize("template", [False, True], ids=["example-template", "own-template"])
def test_a_real_cell_s_directory_is_refused_and_left_as_it_was(
    tmp_path: Path, source: Path, template: bool
) -> None:
    cell = _real_cell(source, tmp_path / "kc2")
    before = _files(cell)
    args = [*CELLCTL, "--cell", str(cell), "emulate", "cell", "--time-scale", "1000"]
    if template:  # its own machines, served in its own directory: the same overwrite
        args += ["--template", str(cell)]
    done = subprocess.run(args, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert done.returncode == 2, done.stdout + done.stderr
    said = " ".join(done.stderr.split())
    toml = cell / "cell.toml"
    assert f"{toml} was not written by cellctl emulate cell" in said, said
    # The ways out: another directory, this cell's machines by --template, or delete it.
    assert "another directory (--cell DIR)" in said, said
    assert f"--template {cell} to serve this cell's machines" in said, said
    assert f"delete {toml} first" in said, said
    assert "listening" not in done.stdout and "wrote" not in done.stdout, done.stdout
    assert _files(cell) == before


def test_the_way_out_serves_that_cell_s_machines_from_another_directory(tmp_path: Path) -> None:
    """What the refusal proposes: --template the real cell, --cell another directory."""
    cell = _real_cell(EXAMPLE_CELL, tmp_path / "mycell")
    before = _files(cell)
    emulated = tmp_path / "emulated"
    args = [*CELLCTL, "--cell", str(emulated), "emulate", "cell", "--template", str(cell)]
    proc = subprocess.Popen(
        [*args, "--time-scale", "1000"], stdout=subprocess.PIPE, text=True, cwd=tmp_path
    )
    try:
        assert proc.stdout is not None
        said = []
        for line in proc.stdout:
            said.append(line)
            if line.strip().startswith("plc"):  # every machine listens
                break
        assert any(f"wrote {emulated / 'cell.toml'}" in line for line in said), said
    finally:
        proc.terminate()
        proc.wait(10)
    assert _files(cell) == before
    edited = next(iter(sorted((cell / "robot").glob("*.aml"))))
    assert (emulated / "robot" / edited.name).read_bytes() == edited.read_bytes()
    assert (emulated / "cell.toml").read_text().startswith("# Emulated cell (time scale 1000)")


def _first_line(toml: Path) -> str:
    return toml.read_text(encoding="utf-8").splitlines()[0]


async def test_a_directory_it_wrote_before_is_emulated_again(tmp_path: Path) -> None:
    """Its own cell.toml (edited since, as the tests' options are) is written anew."""
    directory = tmp_path / "cell"
    first = EmulatedCell(time_scale=1000.0)
    try:
        toml = await first.start(directory)
    finally:
        await first.close()
    toml.write_text(toml.read_text() + "\n# a note of the test's\n")
    again = EmulatedCell(time_scale=500.0)
    try:
        assert await again.start(directory) == toml
        assert _first_line(toml).startswith("# Emulated cell (time scale 500)")
    finally:
        await again.close()


def test_the_demo_removes_no_real_cell_where_it_emulates(tmp_path: Path) -> None:
    """`cellctl demo --out DIR` emulates in DIR/cell, removing what an earlier demo left
    there: a real cell in its place is refused before anything is removed."""
    cell = _real_cell(EXAMPLE_CELL, tmp_path / "out" / "cell")
    before = _files(cell)
    args = [*CELLCTL, "demo", "--parts", "1", "--out", str(tmp_path / "out")]
    done = subprocess.run(args, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert done.returncode == 2, done.stdout + done.stderr
    said = " ".join(done.stderr.split())
    assert f"{cell / 'cell.toml'} was not written by cellctl emulate cell" in said, said
    assert _files(cell) == before
