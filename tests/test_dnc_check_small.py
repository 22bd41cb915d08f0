"""``cellctl dnc check``'s figures for a short program: a wait of a few milliseconds is
said in milliseconds (never ``0.0 s``), and one block is ``1 block``. The real command
line; the check opens no link."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from .conftest import CELLCTL

#: One block that runs in microseconds, then one that takes 30 s: the axes wait once, for
#: the second block's 15 characters (some 17 ms at 9600 baud).
SHORT = "O3\nG90 G01 X0.001 F1000.\nG01 X50. F100.\nM30\n"


def test_a_short_wait_at_one_block_reads_right(tmp_path: Path) -> None:
    shop = tmp_path / "shop"
    shop.mkdir()
    (shop / "dnc.toml").write_text('[machines.mill1]\nlink = "rfc2217://192.0.2.10:4001"\n')
    program = tmp_path / "O3.nc"
    program.write_text(SHORT)
    done = subprocess.run(
        [*CELLCTL, "dnc", "check", "mill1", str(program), "--dir", str(shop)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    said = " ".join(done.stdout.split())
    wait = re.search(r"the axes wait (\S+) s for data at 1 block \(longest (\S+) s, for", said)
    assert wait is not None, said
    # A wait the operator can weigh: its figures, not 0.0 s (nor 0.00 s).
    assert float(wait.group(1)) > 0 and float(wait.group(2)) > 0, said
    assert not re.search(r"(?<![\d.])0\.0+ s", said) and "1 blocks" not in said, said
