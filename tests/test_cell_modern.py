"""examples/cell-modern: a Dyna 2400 and an iso-cnc mill in one cell's routes, run by
`cellctl demo --cell` (every machine emulated behind real ptys, sockets and Modbus/TCP)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from .conftest import CELLCTL

ROOT = Path(__file__).resolve().parent.parent
MODERN = ROOT / "examples" / "cell-modern"


def test_the_modern_cell_checks() -> None:
    done = subprocess.run(
        [*CELLCTL, "--cell", str(MODERN), "cell", "check"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "mills cnc1, cnc2" in " ".join(done.stdout.split())


def test_demo_runs_a_batch_through_a_dyna_2400_and_an_iso_cnc_mill(tmp_path: Path) -> None:
    demo = ["demo", "--cell", str(MODERN), "--parts", "2", "--no-compare", "--time-scale", "200"]
    done = subprocess.run(
        [*CELLCTL, *demo, "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    out = " ".join(done.stdout.split())
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "parts made: 1 x wax-robot-base, 1 x wax-toy-mill-table" in out
    assert "failed steps: 0" in out
    used = re.search(r"utilization cnc2: +([0-9.]+)%", out)
    assert used is not None and float(used.group(1)) > 0  # the iso-cnc mill cut both parts
    assert (tmp_path / "cell" / "gantt.svg").is_file()
