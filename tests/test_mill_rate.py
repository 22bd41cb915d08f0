"""The rate ``cellctl mill download`` shows is the line's at most: its characters over the
time they took on a paced 4800-baud line (writes run ahead of the wire, and the time after
a block's last write is still its sending)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from cellctl.link import LineSettings

from .conftest import CELLCTL, emulator_process

PROGRAMS = Path(__file__).resolve().parent.parent / "examples" / "programs"
LINE = LineSettings.parse("4800,7E2")


def test_the_download_rate_never_passes_the_line(tmp_path: Path) -> None:
    args = ["mill", "--listen", "rfc2217://127.0.0.1:0", "--time-scale", "100"]
    with emulator_process(*args, "--setup-delay", "1") as url:

        def mill(*more: str) -> subprocess.CompletedProcess[str]:
            return subprocess.run(
                [*CELLCTL, "--cell", str(tmp_path), "mill", "--link", url, *more],
                capture_output=True,
                text=True,
                timeout=90,
            )

        init = mill("init", str(PROGRAMS / "cnc1_setup.dyn"))
        assert init.returncode == 0, init.stderr
        down = mill("download", "--time-scale", "100", str(PROGRAMS / "robot_base_rough_cnc1.dyn"))
    assert down.returncode == 0, down.stderr
    shown = down.stdout + down.stderr
    rates = [float(r) for r in re.findall(r"([0-9.]+) chars/s", shown)]
    assert rates, shown
    limit = 1 / LINE.char_time  # 436.4 characters a second at 4800 7E2
    assert 0 < rates[-1] <= limit, (rates[-1], limit, shown)
