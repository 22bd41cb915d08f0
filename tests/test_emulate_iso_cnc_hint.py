"""`cellctl emulate iso-cnc --time-scale N` says what to put in dnc.toml, and a shop made of
exactly that drip-feeds it.

A drip-feed ends at the DNC driver's modelled end of the program's motion: an emulator N
times faster than the real control is matched by `options.motion_scale = N`, which the
printed table carries (at scale 1 the driver would wait the real machine's time). The
emulator runs in its own process, its operator pressing CYCLE START in RMT mode."""

from __future__ import annotations

import subprocess
import tomllib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .conftest import CELLCTL

SCALE = 1000
#: 200 mm at 10 mm/min: 20 minutes of the real control's motion, 1.2 s of the emulator's.
SLOW = "O5000 (SLOW)\nG21 G90 G17\nG01 X0 Y0 F3000\nG01 X200. F10\nM30\n"


@contextmanager
def emulated_control(*args: str) -> Iterator[str]:
    """``cellctl emulate iso-cnc ARGS`` in its own process; yields the dnc.toml table it
    prints (the lines after "feed it with", its ``link`` last)."""
    proc = subprocess.Popen(
        [*CELLCTL, "emulate", "iso-cnc", *args], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        rows: list[str] = []
        for row in proc.stdout:
            if "feed it with" in row or rows:
                rows.append(row)
            if 'link = "' in row:
                break
        assert rows, "the emulator did not say how to feed it"
        yield "".join(rows[1:])
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_the_printed_dnc_toml_drip_feeds_a_scaled_emulator(tmp_path: Path) -> None:
    args = ["--mode", "rmt", "--auto-operator", "--time-scale", str(SCALE)]
    with emulated_control(*args) as table:
        machine = tomllib.loads(table)["machines"]["mill1"]
        assert machine.get("options", {}).get("motion_scale") == SCALE, table
        shop = tmp_path / "shop"
        shop.mkdir()
        (shop / "dnc.toml").write_text(table)
        program = tmp_path / "O5000.nc"
        program.write_text(SLOW)
        drip = subprocess.run(
            [*CELLCTL, "dnc", "drip", "mill1", str(program), "--dir", str(shop)],
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert drip.returncode == 0, drip.stdout + drip.stderr
    assert "O5000.nc: drip-fed" in drip.stdout, drip.stdout


def test_at_its_real_timing_the_table_needs_no_motion_scale(tmp_path: Path) -> None:
    """Scale 1 (the default) is the driver's too; a line not the kind's usual is said."""
    with emulated_control("--line", "19200,8N1") as table:
        machine = tomllib.loads(table)["machines"]["mill1"]
    assert "options" not in machine, table
    assert machine["line"] == "19200,8N1", table
    assert machine["link"], table
