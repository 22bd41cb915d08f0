"""The Dyna 2400 CNC mill, declared for the registry (entry point ``dyna2400`` in
``cellctl.machine_kinds``)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

from cellctl.emulators.serve import scaled_deadline
from cellctl.errors import UsageError
from cellctl.files import read_text
from cellctl.kinds.dyna2400 import dynalan
from cellctl.kinds.dyna2400.options import MillConfig, MillState
from cellctl.kinds.kind import (
    CheckedProgram,
    DriverSpec,
    EmulatorSpec,
    LazyTable,
    MachineKind,
    Preview,
    ProgramLanguage,
    ProgramRole,
)

if TYPE_CHECKING:
    import click

    from cellctl.emulators.serve import EmulatedDevice
    from cellctl.kinds.dyna2400.driver import Dyna2400Mill
    from cellctl.kinds.menu import MachineFunction

# The driver and the emulator are imported by the hooks that use them: the registry reads
# this declaration at every start (`cellctl --help` too).

#: The emulated cell's automatic operator: seconds to power on, press keys, jog to zero.
CELL_OPERATOR = {"power_on": 3.0, "keys": 2.0, "setup": 20.0}


async def _open(spec: DriverSpec) -> Dyna2400Mill:
    from cellctl.kinds.dyna2400.driver import Dyna2400Mill

    assert isinstance(spec.options, MillConfig)
    return await Dyna2400Mill.connect(
        spec.url,
        name=spec.name,
        settings=spec.settings,
        store=spec.store,
        config=spec.options,
        start_output=spec.start_output,
        trace=spec.trace,
        clock=spec.clock,
    )


def _emulator(spec: EmulatorSpec) -> EmulatedDevice:
    from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator, OperatorDelays

    delays = OperatorDelays(**CELL_OPERATOR) if spec.operator else OperatorDelays()
    return Dyna2400Emulator(clock=spec.emulator_clock(), delays=delays)


_ROLES = {
    ProgramRole.SETUP: dynalan.ProgramRole.SETUP,
    ProgramRole.MILLING: dynalan.ProgramRole.MILLING,
}


def validation_context(options: BaseModel, role: ProgramRole) -> dynalan.ValidationContext:
    config = options if isinstance(options, MillConfig) else MillConfig()
    return dynalan.ValidationContext(
        role=_ROLES.get(role, dynalan.ProgramRole.AUTO), config=config.machine()
    )


def _check(path: Path, role: ProgramRole, options: BaseModel) -> CheckedProgram:
    """Parse and validate a DYNALAN program: its problems, lines and machining time."""
    try:
        text = read_text(path, "ascii")
    except OSError as e:
        return CheckedProgram((f"{path}: cannot read: {e.strerror or e}",))
    except UnicodeDecodeError as e:
        return CheckedProgram((f"{path}: cannot read: {e}",))
    program = dynalan.parse_program(text, name=path.name)
    result = dynalan.validate(program, validation_context(options, role))
    seconds = result.toolpath.machining_seconds if result.toolpath else 0.0
    return CheckedProgram(
        tuple(p.format(str(path)) for p in result.errors),
        lines=len(result.program.lines),
        machining_s=seconds,
    )


#: The role a manual function's program plays (for the validator).
_FUNCTION_ROLES = {"init": dynalan.ProgramRole.SETUP, "download": dynalan.ProgramRole.MILLING}


def _check_text(function: str, name: str, text: str, options: BaseModel) -> list[str]:
    """A DYNALAN program a manual function sends: its errors (warnings do not stop it)."""
    config = options if isinstance(options, MillConfig) else MillConfig()
    role = _FUNCTION_ROLES.get(function, dynalan.ProgramRole.AUTO)
    context = dynalan.ValidationContext(role=role, config=config.machine())
    result = dynalan.validate(dynalan.parse_program(text, name=name), context)
    return [p.format(name) for p in result.problems if p.severity is dynalan.Severity.ERROR]


def _split(text: str) -> list[str]:
    blocks = dynalan.split_program(dynalan.parse_program(text))
    return [b.text() for b in blocks]


def _preview(text: str, name: str, options: BaseModel) -> Preview:
    from cellctl.kinds.dyna2400.preview import render_svg

    parsed = dynalan.parse_program(text, name=name)
    config = options if isinstance(options, MillConfig) else MillConfig()
    result = dynalan.validate(parsed, dynalan.ValidationContext(config=config.machine()))
    if result.toolpath is None:
        first = result.errors[0].format(name) if result.errors else ""
        raise UsageError(f"cannot trace {Path(name).stem}: {first or 'no toolpath'}")
    return Preview(render_svg(result.toolpath, title=name), result.toolpath.blocks)


def _emulated_options(scale: float) -> dict[str, float]:
    return {
        "setup_timeout": scaled_deadline(120.0, scale),
        "block_extra": scaled_deadline(60.0, scale),
        # The estimate a block's deadline multiplies is in the real cell's time.
        "block_margin": 2.0 / scale,
        "ready_wait": 2.0,
        # The cut estimate behind the progress and the time left is in the real cell's time.
        "time_scale": scale,
    }


def _condition(status: Any) -> Any:
    return status.kind_condition


def _menu() -> Sequence[MachineFunction]:
    from cellctl.kinds.dyna2400.menu import MENU

    return MENU


def _commands() -> Sequence[tuple[str, click.Command]]:
    from cellctl.kinds.dyna2400.cli import emulate_mill, mill

    return [("", mill), ("emulate", emulate_mill)]


def _timing() -> Any:
    from cellctl.kinds.dyna2400.timing import CutModel

    return CutModel()


DYNA2400 = MachineKind(
    name="dyna2400",
    family="mill",
    maker="Dyna",
    model="2400 CNC mill",
    line="4800,7E2",
    options=MillConfig,
    open_driver=_open,
    emulator=_emulator,
    states=MillState,
    condition=_condition,
    language=ProgramLanguage(suffix=".dyn", check=_check, split=_split, preview=_preview),
    menu=_menu,
    commands=_commands,
    command_names=(("", "mill"), ("emulate", "mill")),
    timing=_timing,
    emulated_options=_emulated_options,
    needs_setup=True,
    check_text=_check_text,
    faults=LazyTable("cellctl.kinds.dyna2400.emulator:FAULTS"),
    description="3-axis CNC mill: DYNALAN blocks streamed as the controller's CTS asks",
)
