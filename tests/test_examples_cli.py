"""`cellctl examples`: what ships, listed from its one table, and `examples copy`, which gives a
user the README's examples/ as files of their own, never over anything that exists and never
through a link. Run from the repository (tests/test_wheel.py runs it from the installed wheel).
"""

from __future__ import annotations

import os
import stat
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from cellctl.ui.cli import main
from cellctl.ui.examples_cli import EXAMPLES

from .conftest import CELLCTL
from .test_cli_startup import CELLCTL as ENTRY_POINT
from .test_cli_startup import _heavy, _imported

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = ROOT / "src" / "cellctl" / "examples"


def cellctl(*args: str) -> Result:
    """``cellctl ARGS`` on the real command line, in this process."""
    return CliRunner().invoke(main, list(args))


def tree(directory: Path) -> dict[str, bytes | None]:
    """Every entry under ``directory`` by relative path: a file's bytes, None for a directory."""
    return {
        p.relative_to(directory).as_posix(): None if p.is_dir() else p.read_bytes()
        for p in sorted(directory.rglob("*"))
    }


@pytest.fixture
def strict_umask() -> Iterator[None]:
    """A umask that would make every new file private: the copy's modes must not follow it."""
    old = os.umask(0o077)
    try:
        yield
    finally:
        os.umask(old)


def test_the_listing_is_one_line_per_example_that_ships() -> None:
    assert set(EXAMPLES) == {p.name for p in SHIPPED.iterdir() if p.is_dir()}
    done = cellctl("examples")
    assert done.exit_code == 0, done.output
    lines = done.stdout.splitlines()
    assert [line.split()[0] for line in lines] == list(EXAMPLES)
    for line, what in zip(lines, EXAMPLES.values(), strict=True):
        assert line.endswith(what) and len(line) <= 80, line


def test_listing_and_copying_import_nothing_of_the_cell(tmp_path: Path) -> None:
    for args in (["examples"], ["examples", "copy", "--only", "robot", "out"]):
        done, modules = _imported(tmp_path, ENTRY_POINT, *args)
        assert done.returncode == 0, done.stderr[-2000:]
        assert "cellctl.ui.examples_cli" in modules
        assert not _heavy(modules), f"cellctl {' '.join(args)} imported {_heavy(modules)}"
    assert (tmp_path / "out" / "robot" / "conveyor_to_cnc1.aml").is_file()


def test_copy_gives_every_file_as_the_users_own(tmp_path: Path, strict_umask: None) -> None:
    target = tmp_path / "new" / "examples"  # its parent is missing too
    done = cellctl("examples", "copy", str(target))
    assert done.exit_code == 0, done.output
    assert tree(target) == tree(SHIPPED)
    files = [p for p in target.rglob("*") if p.is_file()]
    assert f"copied {len(files)} files to {target}" in done.stdout
    assert {stat.S_IMODE(p.stat().st_mode) for p in files} == {0o644}
    dirs = [target, *(p for p in target.rglob("*") if p.is_dir())]
    assert {stat.S_IMODE(p.stat().st_mode) for p in dirs} == {0o755}
    assert not any(p.is_symlink() for p in target.rglob("*"))


def test_a_copied_cell_is_a_whole_cell(tmp_path: Path) -> None:
    assert cellctl("examples", "copy", str(tmp_path)).exit_code == 0
    for name in ("cell", "cell-modern", "cell-tending"):
        checked = cellctl("--cell", str(tmp_path / name), "cell", "check")
        assert checked.exit_code == 0, checked.output
        assert f"{tmp_path / name / 'cell.toml'}: ok" in checked.stdout


def test_only_copies_the_examples_named(tmp_path: Path) -> None:
    done = cellctl("examples", "copy", "--only", "cell-tending", "--only", "robot", str(tmp_path))
    assert done.exit_code == 0, done.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cell-tending", "robot"]
    assert tree(tmp_path / "cell-tending") == tree(SHIPPED / "cell-tending")
    unknown = cellctl("examples", "copy", "--only", "cell-nowhere", str(tmp_path / "x"))
    assert unknown.exit_code == 2 and "cell-nowhere" in unknown.stderr
    assert not (tmp_path / "x").exists()


def test_an_example_there_refuses_the_copy_before_anything_is_written(tmp_path: Path) -> None:
    # "programs" comes after "cell", "cell-modern" and "cell-tending": none of them is made.
    (tmp_path / "programs").write_text("my notes\n")
    before = tree(tmp_path)
    done = cellctl("examples", "copy", str(tmp_path))
    assert done.exit_code == 2, done.output
    assert f"error: {tmp_path / 'programs'} exists: nothing copied" in done.stderr
    assert tree(tmp_path) == before


def test_a_link_is_never_written_through(tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "link").symlink_to(elsewhere)
    done = cellctl("examples", "copy", str(tmp_path / "link"))
    assert done.exit_code == 2, done.output
    assert f"{tmp_path / 'link'}: a symbolic link (to {elsewhere})" in done.stderr
    # A dangling link where an example would go is there: refused, its target never made.
    target = tmp_path / "target"
    target.mkdir()
    (target / "robot").symlink_to(elsewhere / "robot")
    done = cellctl("examples", "copy", "--only", "robot", str(target))
    assert done.exit_code == 2 and f"{target / 'robot'} exists" in done.stderr
    assert list(elsewhere.iterdir()) == []
    assert [p.name for p in target.iterdir()] == ["robot"]


def test_a_file_in_the_way_of_the_directory_is_refused(tmp_path: Path) -> None:
    (tmp_path / "examples").write_text("not a directory\n")
    done = cellctl("examples", "copy", str(tmp_path / "examples"))
    assert done.exit_code == 2
    assert f"{tmp_path / 'examples'}: not a directory" in done.stderr
    assert (tmp_path / "examples").read_text() == "not a directory\n"


def test_the_default_is_examples_in_the_working_directory(tmp_path: Path) -> None:
    done = subprocess.run(
        [*CELLCTL, "examples", "copy"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert tree(tmp_path / "examples") == tree(SHIPPED)
    # The README's paths, as a wheel user types them, now read the copy.
    check = subprocess.run(
        [*CELLCTL, "mill", "check", "examples/programs/broken/feed_too_fast.dyn"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert check.returncode == 1
    assert "examples/programs/broken/feed_too_fast.dyn:2:14: error [feed-range]" in check.stdout
