"""``cellctl mill`` and ``cellctl emulate mill`` as a user runs them: separate processes, a real
RFC 2217 socket between them."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.ui.cli import main

from .conftest import CELLCTL, emulator_process

PROGRAMS = Path(__file__).resolve().parent.parent / "examples" / "programs"


def test_check_lists_every_problem_and_fails_on_errors() -> None:
    result = CliRunner().invoke(
        main, ["mill", "check", str(PROGRAMS / "broken" / "arc_over_180.dyn")]
    )
    assert result.exit_code == 1
    assert "arc_over_180.dyn:6:5: error [arc] line 005: arc of 270 degrees" in result.output
    assert "1 error(s)" in result.output


def test_check_passes_a_good_program_with_its_blocks() -> None:
    path = PROGRAMS / "toy_mill_table_finish_cnc2.dyn"
    result = CliRunner().invoke(main, ["mill", "check", str(path)])
    assert result.exit_code == 0, result.output
    assert "3 block(s)" in result.output


@pytest.mark.parametrize("suffix", [".svg", ".png"])
def test_preview_draws_the_toolpath_with_block_marks(tmp_path: Path, suffix: str) -> None:
    out = tmp_path / f"table{suffix}"
    path = PROGRAMS / "toy_mill_table_finish_cnc2.dyn"
    result = CliRunner().invoke(main, ["mill", "preview", str(path), "-o", str(out)])
    assert result.exit_code == 0, result.output
    data = out.read_bytes()
    if suffix == ".svg":
        assert data.count(b'class="block-start"') == 3
    else:
        assert data.startswith(b"\x89PNG")


def test_missing_program_is_refused_with_one_line() -> None:
    result = CliRunner().invoke(main, ["mill", "check", "nowhere.dyn"])
    assert result.exit_code == 2
    assert "file not found" in result.output


@pytest.fixture
def emulator() -> Iterator[str]:
    """``cellctl emulate mill`` in its own process over RFC 2217; yields its URL."""
    args = ["mill", "--listen", "rfc2217://127.0.0.1:0", "--time-scale", "2000", "--no-pacing"]
    with emulator_process(*args, "--line", "115200,8N1", "--setup-delay", "400") as url:
        assert url.startswith("rfc2217://")
        yield url


def _mill(url: str, cell: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "--cell", str(cell), "mill", "--link", url, "--line", "115200,8N1", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_cli_session_init_download_status_end(emulator: str, tmp_path: Path) -> None:
    init = _mill(emulator, tmp_path, "init", str(PROGRAMS / "cnc2_setup.dyn"))
    assert init.returncode == 0, init.stderr
    assert "Initializing was correct" in init.stdout
    again = _mill(emulator, tmp_path, "init", str(PROGRAMS / "cnc2_setup.dyn"))
    assert again.returncode == 5 and "Machine already initialized" in again.stderr
    trace = tmp_path / "mill.trace"
    down = _mill(
        emulator,
        tmp_path,
        "--trace",
        str(trace),
        "download",
        str(PROGRAMS / "robot_arm_finish_cnc2.dyn"),
    )
    assert down.returncode == 0, down.stderr
    assert "Download was correct" in down.stdout
    assert trace.stat().st_size > 0
    status = _mill(emulator, tmp_path, "status")
    assert "state 2 (Initialized)" in status.stdout
    bad = _mill(emulator, tmp_path, "download", str(PROGRAMS / "broken" / "outside_travel.dyn"))
    assert bad.returncode == 2 and "Not a valid program" in bad.stderr
    end = _mill(emulator, tmp_path, "end")
    assert "Ending was correct" in end.stdout
    # END leaves the controller in manual (state 0) until its operator readies it again
    # (state 1): then the mill initializes anew.
    deadline = time.monotonic() + 30
    while (
        "state 1 (Uninitialized, Ready" not in (shown := _mill(emulator, tmp_path, "status")).stdout
    ):
        assert "state 0" in shown.stdout, shown.stdout + shown.stderr
        assert time.monotonic() < deadline, "the operator never readied the mill again"
        time.sleep(0.1)
    init = _mill(emulator, tmp_path, "init", str(PROGRAMS / "cnc2_setup.dyn"))
    assert init.returncode == 0 and "Initializing was correct" in init.stdout, init.stderr
