"""cellctl installed as users install it: the wheel, in a fresh venv, run from an empty
directory (``cellctl demo``, ``demo --factory 2``, ``emulate cell``, ``examples copy`` and the
README's checks on the copied files), with nothing of the repository on the path.

How the venv gets its dependencies: the wheel goes in with ``--no-deps``, and a ``.pth`` file
adds this test run's site-packages after the venv's own, so the dependencies resolve there
without a download (the test stays offline and quick). Python does not read the ``.pth`` files
of a directory that a ``.pth`` file adds, so the editable install of cellctl in that
site-packages stays out: the test checks that ``cellctl`` is imported from the fresh venv.
"""

from __future__ import annotations

import os
import queue
import shutil
import signal
import subprocess
import sys
import sysconfig
import threading
import time
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "src" / "cellctl" / "examples"
EXAMPLE = EXAMPLES / "cell"
#: This run's pip, offline: the wheel is built and installed with no download.
PIP = [sys.executable, "-m", "pip", "-q", "--no-input"]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel, built from a copy of the sources (a build leaves build/ behind, whose stale
    files would go into later wheels)."""
    work = tmp_path_factory.mktemp("build")
    source = work / "source"
    shutil.copytree(
        ROOT / "src", source / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info")
    )
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, source / name)
    out = work / "dist"
    subprocess.run(
        [*PIP, "wheel", "--no-index", "--no-deps", "--no-build-isolation", "-w", str(out), source],
        check=True,
        timeout=120,
    )
    (found,) = out.glob("cellctl-*.whl")
    return found


@pytest.fixture(scope="module")
def venv(wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh venv with the wheel installed (not editable); returns its bin/."""
    home = tmp_path_factory.mktemp("venv") / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(home)], check=True)
    python = home / "bin" / "python"
    subprocess.run(
        [*PIP, "--python", str(python), "install", "--no-index", "--no-deps", str(wheel)],
        check=True,
        timeout=120,
    )
    purelib = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    deps = sysconfig.get_path("purelib")  # this test run's: the dependencies
    (Path(purelib) / "zz_cellctl_test_deps.pth").write_text(deps + "\n")
    return home / "bin"


def clean_env() -> dict[str, str]:
    """The environment without this run's venv on PATH, nothing on PYTHONPATH, no --cell."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("CELLCTL_", "PYTHON"))}
    bindir = str(Path(sys.executable).parent)
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if p != bindir)
    return env


@pytest.fixture
def empty(tmp_path: Path) -> Path:
    """An empty directory to run from: no examples/, no src/ next to it."""
    directory = tmp_path / "empty"
    directory.mkdir()
    return directory


def test_the_wheel_carries_every_example_and_the_license(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = sorted(p.relative_to(EXAMPLES).as_posix() for p in EXAMPLES.rglob("*") if p.is_file())
    for part in ("cell/cell.toml", "cell/programs/", "cell/robot/", "robot/", "programs/broken/"):
        assert any(p.startswith(part) for p in shipped), part
    for suffix in (".aml", ".dyn", ".nc", ".script", ".toml", ".txt"):
        assert any(p.endswith(suffix) for p in shipped), suffix
    missing = [p for p in shipped if f"cellctl/examples/{p}" not in names]
    assert missing == [], f"not in the wheel: {missing}"
    version = wheel.name.split("-")[1]
    license_text = zipfile.ZipFile(wheel).read(f"cellctl-{version}.dist-info/licenses/LICENSE")
    assert license_text == (ROOT / "LICENSE").read_bytes()
    assert b"MIT License" in license_text


def test_each_repository_example_is_the_packaged_one() -> None:
    # One copy: each examples/NAME links to the package's data, so both read the same files.
    linked = sorted(p.name for p in (ROOT / "examples").iterdir() if p.is_symlink())
    assert linked == sorted(p.name for p in EXAMPLES.iterdir() if p.is_dir())
    for name in linked:
        assert (ROOT / "examples" / name).resolve() == (EXAMPLES / name).resolve()
    assert (ROOT / "examples" / "cell" / "cell.toml").is_file()


def test_cellctl_runs_from_the_installed_wheel(venv: Path, empty: Path) -> None:
    where = subprocess.run(
        [str(venv / "python"), "-c", "import cellctl; print(cellctl.__file__)"],
        cwd=empty,
        env=clean_env(),
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    assert Path(where).is_relative_to(venv.parent), where
    assert not Path(where).is_relative_to(ROOT), where


def test_demo_from_an_empty_directory(venv: Path, empty: Path) -> None:
    result = subprocess.run(
        [str(venv / "cellctl"), "demo", "--parts", "2", "--no-compare", "--time-scale", "1000"],
        cwd=empty,
        env=clean_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "parts made: 1 x wax-robot-base, 1 x wax-toy-mill-table" in result.stdout
    assert (empty / "demo-out" / "cell" / "gantt.svg").is_file()
    programs = {p.name for p in (empty / "demo-out" / "cell" / "programs").iterdir()}
    assert programs == {p.name for p in (EXAMPLE / "programs").iterdir()}


def test_factory_demo_from_an_empty_directory(venv: Path, empty: Path) -> None:
    result = subprocess.run(
        [str(venv / "cellctl"), "demo", "--factory", "2", "--parts", "2", "--time-scale", "1000"],
        cwd=empty,
        env=clean_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "total: 2 orders (2 done), parts made 2 of 2" in result.stdout, result.stdout


def lines_of(proc: subprocess.Popen[str]) -> queue.Queue[str | None]:
    """A queue the process's output lines arrive in, then None at its end (read by a thread,
    so that every wait has a deadline)."""
    lines: queue.Queue[str | None] = queue.Queue()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return lines


def wait_for(lines: queue.Queue[str | None], text: str, timeout: float) -> list[str]:
    """The lines up to the first that contains ``text``; fails at the deadline or the end."""
    seen: list[str] = []
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        try:
            line = lines.get(timeout=left)
        except queue.Empty:
            break
        if line is None:
            raise AssertionError(f"ended before {text!r}; output: {''.join(seen)}")
        seen.append(line)
        if text in line:
            return seen
    raise AssertionError(f"no {text!r} within {timeout} s; output: {''.join(seen)}")


def test_emulate_cell_from_an_empty_directory(venv: Path, empty: Path) -> None:
    env = clean_env()
    proc = subprocess.Popen(
        [str(venv / "cellctl"), "--cell", "mycell", "emulate", "cell", "--time-scale", "100"],
        cwd=empty,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        lines = lines_of(proc)
        wait_for(lines, "plc ", timeout=30)
        cell = empty / "mycell"
        for sub in ("robot", "programs"):
            copied = sorted(p.name for p in (cell / sub).iterdir())
            assert copied == sorted(p.name for p in (EXAMPLE / sub).iterdir())
        check = subprocess.run(
            [str(venv / "cellctl"), "--cell", "mycell", "cell", "check"],
            cwd=empty,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert check.returncode == 0, check.stdout + check.stderr
        proc.send_signal(signal.SIGINT)
        wait_for(lines, "emulated cell stopped", timeout=30)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def cellctl_in(venv: Path, directory: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``cellctl ARGS`` of the installed wheel, run in ``directory``."""
    return subprocess.run(
        [str(venv / "cellctl"), *args],
        cwd=directory,
        env=clean_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_the_readme_tour_works_on_the_copied_examples(venv: Path, empty: Path) -> None:
    copied = cellctl_in(venv, empty, "examples", "copy")
    assert copied.returncode == 0, copied.stdout + copied.stderr
    here = sorted(p.relative_to(empty / "examples") for p in (empty / "examples").rglob("*"))
    assert here == sorted(p.relative_to(EXAMPLES) for p in EXAMPLES.rglob("*"))
    assert (empty / "examples" / "robot" / "conveyor_to_cnc1.aml").read_bytes() == (
        EXAMPLES / "robot" / "conveyor_to_cnc1.aml"
    ).read_bytes()

    check = cellctl_in(
        venv,
        empty,
        "program",
        "check",
        "examples/robot/conveyor_to_cnc1.aml",
        "examples/cell-tending/programs/O1001.nc",
    )
    assert check.returncode == 0, check.stdout + check.stderr
    assert "examples/robot/conveyor_to_cnc1.aml: a good ibm7545 program" in check.stdout
    assert "examples/cell-tending/programs/O1001.nc: a good iso-cnc program" in check.stdout

    broken = cellctl_in(venv, empty, "mill", "check", "examples/programs/broken/feed_too_fast.dyn")
    assert broken.returncode == 1, broken.stdout + broken.stderr
    assert "feed_too_fast.dyn:2:14: error [feed-range]" in broken.stdout
    assert "1 error(s), 0 warning(s)" in broken.stdout


def test_examples_copy_from_the_wheel_never_overwrites(venv: Path, empty: Path) -> None:
    notes = empty / "examples" / "cell-tending" / "cell.toml"
    notes.parent.mkdir(parents=True)
    notes.write_text("# my own\n")
    refused = cellctl_in(venv, empty, "examples", "copy")
    assert refused.returncode == 2, refused.stdout + refused.stderr
    assert "examples/cell-tending exists: nothing copied" in refused.stderr
    assert notes.read_text() == "# my own\n"
    assert sorted(p.name for p in (empty / "examples").iterdir()) == ["cell-tending"]
    # The one not there copies beside it.
    alone = cellctl_in(venv, empty, "examples", "copy", "--only", "robot")
    assert alone.returncode == 0, alone.stdout + alone.stderr
    assert sorted(p.name for p in (empty / "examples").iterdir()) == ["cell-tending", "robot"]
