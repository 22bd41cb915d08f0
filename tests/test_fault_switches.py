"""Every emulator's fault switches: an argument only where the table says one (``=ARG: ...``),
refused in words elsewhere, from the table, the command line and a plan alike."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from cellctl.emulators.plc import FAULTS as PLC_FAULTS
from cellctl.emulators.switches import takes_argument
from cellctl.errors import UsageError
from cellctl.kinds import registry
from cellctl.plan.faults import check_switch as plan_check

from .conftest import CELLCTL

ROOT = Path(__file__).resolve().parent.parent


def every_switch() -> list[tuple[str | None, str]]:
    """Each fault switch there is: (its kind, or None for the PLC's; its name)."""
    found: list[tuple[str | None, str]] = [(None, name) for name in PLC_FAULTS]
    for kind in registry.names():
        found += [(kind, name) for name in registry.kind(kind).faults]
    return found


@pytest.mark.parametrize(("kind", "name"), every_switch())
def test_an_argument_only_where_the_table_says(kind: str | None, name: str) -> None:
    machine = kind or "plc"
    if takes_argument(registry.kind(kind).faults if kind else PLC_FAULTS, name):
        with pytest.raises(UsageError):  # a word where its number belongs
            plan_check(machine, kind, name, "not-a-value")
    else:
        plan_check(machine, kind, name, None)  # switched on in a fresh emulator: fine
        with pytest.raises(UsageError, match=f"fault {name} takes no argument, not 'abc'"):
            plan_check(machine, kind, name, "abc")


def test_the_command_line_and_a_plan_refuse_an_argument_the_switch_does_not_take(
    tmp_path: Path,
) -> None:
    emulate = subprocess.run(
        [*CELLCTL, "emulate", "mill", "--listen", "socket://127.0.0.1:0", "--fault", "stall=abc"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert emulate.returncode == 2, emulate.stderr
    assert "fault stall takes no argument, not 'abc'" in emulate.stderr
    plan = subprocess.run(
        [*CELLCTL, "plan", "--dir", str(ROOT / "examples" / "cell"), "--start", "08:00",
         "--add", "wax-robot-base:1", "--fault", "cnc2:stall=abc@09:00-10:00"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )  # fmt: skip
    assert plan.returncode == 2, plan.stderr
    assert "fault stall takes no argument, not 'abc'" in plan.stderr
    assert "Traceback" not in plan.stderr
