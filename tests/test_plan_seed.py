"""`cellctl plan --seed N` seeds what is random in the plan's emulated machines (a line's
noise): the same seed plays the same plan, another seed another one under noise; a noise
fault given its own SEED keeps it, whatever the plan's seed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.ui.cli import main

START = "2026-11-25T06:00"


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("plan-seed") / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    return directory


def played(cell: Path, seed: int, noise: str = "noise=3e-3") -> Any:
    """The steps, alarms and finish times of a plan with a noisy robot line."""
    result = CliRunner().invoke(
        main,
        ["plan", "--dir", str(cell), "--add", "wax-robot-base:2", "--start", START,
         "--shift", "2h", "--fault", f"robot:{noise}@06:00-07:00", "--seed", str(seed),
         "--json"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output + repr(result.exception)
    [plan] = json.loads(result.output)["plans"]
    assert plan["seed"] == seed
    return plan["steps"], plan["alarms_raised"], [o["finished"] for o in plan["orders"]]


@pytest.mark.timeout(600)  # plays on a busy box: CPU, not waiting
def test_the_seed_seeds_the_machines_noise(cell: Path) -> None:
    plans = {seed: played(cell, seed) for seed in (0, 5, 99)}
    # Another seed, other draws: the noise garbles other bytes, the steps differ.
    assert len({json.dumps(p) for p in plans.values()}) > 1
    # The same seed, the same plan.
    assert played(cell, 5) == plans[5]


@pytest.mark.timeout(600)
def test_a_noise_with_its_own_seed_keeps_it(cell: Path) -> None:
    assert played(cell, 0, "noise=3e-3,7") == played(cell, 99, "noise=3e-3,7")
