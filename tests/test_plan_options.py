"""A plan plays the real cell's configuration as it is: the options a cell sets for its
machines (a tighter block deadline, a longer setup time) are played, not replaced by the
defaults a kind gives an emulation (docs/plan.md: "the configuration it plays ... is the real
cell's")."""

from __future__ import annotations

import shutil
import tomllib
from pathlib import Path

import pytest

from cellctl.clock import current_clock
from cellctl.emulators.cell import EXAMPLE_CELL, EmulatedCell


@pytest.mark.virtual
async def test_the_cells_own_machine_options_are_played_on_the_machines_time(
    tmp_path: Path,
) -> None:
    template = tmp_path / "real"
    shutil.copytree(EXAMPLE_CELL, template)
    with (template / "cell.toml").open("a") as toml:
        toml.write("\n[machines.cnc1.options]\nblock_margin = 0.5\nsetup_timeout = 77\n")
    cell = EmulatedCell(clock=current_clock(), links="mem", template=template)
    try:
        await cell.start(tmp_path / "played")
    finally:
        await cell.close()
    played = tomllib.loads((tmp_path / "played" / "cell.toml").read_text())
    cnc1 = played["machines"]["cnc1"]["options"]
    # The cell's own, kept; what it leaves unset, the kind's for its emulation.
    assert (cnc1["block_margin"], cnc1["setup_timeout"]) == (0.5, 77)
    assert cnc1["time_scale"] == 1 and "block_extra" in cnc1
    # A mill the cell says nothing of: the kind's emulated options, as before.
    assert played["machines"]["cnc2"]["options"]["block_margin"] == 2.0
