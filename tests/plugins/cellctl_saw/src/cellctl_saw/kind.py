"""The Kerf 100, declared for cellctl's registry: everything cellctl knows of the saw."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

from cellctl.emulators.serve import EmulatedDevice, scaled_deadline
from cellctl.kinds.kind import (
    CheckedProgram,
    DriverSpec,
    EmulatorSpec,
    LazyTable,
    MachineKind,
    ProgramLanguage,
    ProgramRole,
)
from cellctl.kinds.menu import MachineFunction
from cellctl_saw.options import SawOptions
from cellctl_saw.protocol import SawState, parse_cut_list

if TYPE_CHECKING:
    from cellctl_saw.driver import KerfSaw

# cellctl reads this declaration at every start: the driver and the emulator are imported
# by the hooks that use them.


async def _open(spec: DriverSpec) -> KerfSaw:
    from cellctl_saw.driver import KerfSaw

    assert isinstance(spec.options, SawOptions)
    return await KerfSaw.connect(
        spec.url,
        name=spec.name,
        settings=spec.settings,
        store=spec.store,
        options=spec.options,
        trace=spec.trace,
    )


def _emulator(spec: EmulatorSpec) -> EmulatedDevice:
    from cellctl_saw.emulator import KerfEmulator

    return KerfEmulator(clock=spec.emulator_clock())


def _max_length(options: BaseModel) -> float:
    return options.max_length_mm if isinstance(options, SawOptions) else SawOptions().max_length_mm


def _check(path: Path, role: ProgramRole, options: BaseModel) -> CheckedProgram:
    """A cut list file: its problems, lines and cutting time."""
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as e:
        return CheckedProgram((f"{path}: cannot read: {e}",))
    setup = {ProgramRole.SETUP: True, ProgramRole.MILLING: False}.get(role)
    found = parse_cut_list(text, str(path), setup=setup, max_length_mm=_max_length(options))
    return CheckedProgram(found.problems, lines=found.lines, machining_s=found.seconds)


def _check_text(function: str, name: str, text: str, options: BaseModel) -> list[str]:
    """A program a manual function takes (the console checks it before it is sent)."""
    found = parse_cut_list(text, name, setup=False, max_length_mm=_max_length(options))
    return list(found.problems)


def _condition(status: Any) -> Any:
    return status.kind_condition


def _menu() -> Sequence[MachineFunction]:
    from cellctl_saw.menu import MENU

    return MENU


def _emulated_options(scale: float) -> dict[str, float]:
    return {
        "cut_margin": 2.0 / scale,
        "cut_extra": scaled_deadline(30.0, scale),
        "home_timeout": scaled_deadline(10.0, scale),
    }


KERF100 = MachineKind(
    name="kerf100",
    family="mill",
    maker="Kerf",
    model="100 bar saw",
    line="9600,8N1",
    options=SawOptions,
    open_driver=_open,
    emulator=_emulator,
    states=SawState,
    condition=_condition,
    language=ProgramLanguage(suffix=".cut", check=_check),
    menu=_menu,
    emulated_options=_emulated_options,
    needs_setup=True,
    program_files=(".cut",),
    check_text=_check_text,
    faults=LazyTable("cellctl_saw.emulator:FAULTS"),
    description="single-axis bar saw: cut lists over an ASCII line protocol",
)
