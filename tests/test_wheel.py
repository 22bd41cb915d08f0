"""cellctl installed as users install it: the wheel, in a fresh venv, run from an empty
directory (``cellctl demo``, ``demo --factory 2``, ``emulate cell``), with nothing of the
repository on the path.

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
EXAMPLE = ROOT / "src" / "cellctl" / "examples" / "cell"
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
    for name in ("pyproject.toml", "README.md"):
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


def test_the_wheel_carries_the_example_cell(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = sorted(p.relative_to(EXAMPLE).as_posix() for p in EXAMPLE.rglob("*") if p.is_file())
    assert "cell.toml" in shipped and any(p.startswith("programs/") for p in shipped)
    assert any(p.startswith("robot/") for p in shipped)
    missing = [p for p in shipped if f"cellctl/examples/cell/{p}" not in names]
    assert missing == [], f"not in the wheel: {missing}"


def test_the_repository_examples_cell_is_the_packaged_one() -> None:
    # One copy: examples/cell links to the package's data, so both read the same files.
    assert (ROOT / "examples" / "cell").resolve() == EXAMPLE.resolve()
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
