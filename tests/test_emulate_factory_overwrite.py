"""`cellctl emulate factory DIR` and `cellctl demo --factory N --out DIR` next to a real
factory: refused before a file is touched.

A factory.toml that an emulated factory did not write (no "# Emulated factory of N cells
(time scale ...)" first line) is a factory's own configuration, and a cell directory in it
with a cell.toml an emulated cell did not write is a cell's own. The demo clears
``DIR/factory`` before it starts, and `emulate factory` writes factory.toml and the cells:
either would replace them. A directory an emulation wrote before is emulated again."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from cellctl.emulators.cell import EMULATED_HEADER, EXAMPLE_CELL
from cellctl.errors import UsageError
from cellctl.factory.emulated import EMULATED_FACTORY_HEADER, check_factory_dir

from .conftest import CELLCTL

REAL_FACTORY = """[factory]
name = "plant 7"

[broker]
url = "mqtt://127.0.0.1:1883"

[cells.cell1]
prefix = "cellctl/cell1"
"""


def _files(directory: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(directory)): p.read_bytes()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def _real_factory(directory: Path, *, real_toml: bool) -> Path:
    """A factory's directory: its own factory.toml, or an emulated one holding a real cell."""
    directory.mkdir(parents=True)
    if real_toml:
        (directory / "factory.toml").write_text(REAL_FACTORY)
    else:
        (directory / "factory.toml").write_text(
            "# Emulated factory of 2 cells (time scale 1000); written by cellctl emulate "
            "factory.\n" + REAL_FACTORY
        )
        shutil.copytree(EXAMPLE_CELL, directory / "cell1")  # a real cell's cell.toml
    return directory


def _refusal(args: list[str], cwd: Path) -> str:
    done = subprocess.run(args, capture_output=True, text=True, timeout=60, cwd=cwd)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Mosquitto" not in done.stdout, done.stdout  # refused before anything started
    return " ".join(done.stderr.split())


@pytest.mark.parametrize("real_toml", [True, False], ids=["factory-toml", "cell-toml"])
def test_the_factory_demo_refuses_a_real_factory_in_its_out_directory(
    tmp_path: Path, real_toml: bool
) -> None:
    plant = _real_factory(tmp_path / "out" / "factory", real_toml=real_toml)
    before = _files(plant)
    args = [*CELLCTL, "demo", "--factory", "2", "--parts", "2", "--out", str(tmp_path / "out")]
    said = _refusal(args, tmp_path)
    if real_toml:
        assert f"{plant / 'factory.toml'} was not written by cellctl emulate factory" in said
        assert f"delete {plant / 'factory.toml'} first" in said, said
    else:
        assert f"{plant / 'cell1' / 'cell.toml'} was not written by cellctl emulate cell" in said
    assert _files(plant) == before


def test_emulate_factory_refuses_a_real_factory_s_directory(tmp_path: Path) -> None:
    plant = _real_factory(tmp_path / "plant", real_toml=True)
    before = _files(plant)
    said = _refusal([*CELLCTL, "emulate", "factory", "--cells", "2", str(plant)], tmp_path)
    assert f"{plant / 'factory.toml'} was not written by cellctl emulate factory" in said, said
    assert _files(plant) == before


def test_a_directory_an_emulation_wrote_is_its_own_to_write_again(tmp_path: Path) -> None:
    plant = tmp_path / "plant"
    (plant / "cell1").mkdir(parents=True)
    (plant / "broker").mkdir()
    header = EMULATED_FACTORY_HEADER.format(cells=2, scale=1000)
    (plant / "factory.toml").write_text(header + "\n" + REAL_FACTORY)
    (plant / "cell1" / "cell.toml").write_text(EMULATED_HEADER.format(scale=1000) + "\n")
    check_factory_dir(plant)  # no refusal: an emulated factory and cell
    check_factory_dir(tmp_path / "nothing-yet")  # nor for a directory not made yet
    (plant / "cell1" / "cell.toml").write_text("[cell]\n")
    with pytest.raises(UsageError, match="was not written by cellctl emulate cell"):
        check_factory_dir(plant)
