"""The IBM 7545 and its variant the 7547, declared for the registry (entry points
``ibm7545`` and ``ibm7547`` in ``cellctl.machine_kinds``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

from cellctl.errors import CellctlError, UsageError
from cellctl.files import read_text
from cellctl.kinds.ibm7545.options import RobotConfig, RobotState, robot_condition
from cellctl.kinds.kind import (
    CheckedProgram,
    DriverSpec,
    EmulatorSpec,
    LazyTable,
    MachineKind,
    ProgramLanguage,
    ProgramRole,
)

if TYPE_CHECKING:
    import click

    from cellctl.emulators.serve import EmulatedDevice
    from cellctl.kinds.ibm7545.driver import Ibm7545Robot
    from cellctl.kinds.menu import MachineFunction

# The driver, the emulator and the compiler are imported by the hooks that use them: the
# registry reads this declaration at every start (`cellctl --help` too).


async def _open(spec: DriverSpec) -> Ibm7545Robot:
    from cellctl.kinds.ibm7545.driver import Ibm7545Robot

    assert isinstance(spec.options, RobotConfig)
    return await Ibm7545Robot.connect(
        spec.url,
        name=spec.name,
        settings=spec.settings,
        store=spec.store,
        config=spec.options,
        trace=spec.trace,
        clock=spec.clock,
    )


def _emulator(spec: EmulatorSpec) -> EmulatedDevice:
    from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator

    return Ibm7545Emulator(clock=spec.emulator_clock())


def application_name(program: str) -> str:
    """The controller's application name of a transfer program: ``cnc1_to_cnc2`` ->
    ``CNC1TOCN`` (at most 8 characters)."""
    return program.upper().replace("_", "")[:8]


def _check(path: Path, role: ProgramRole, options: BaseModel) -> CheckedProgram:
    """Compile an AML/E source; its problems in the compiler's words."""
    from cellctl.kinds.ibm7545.aml import compile_source

    try:
        source = read_text(path)
    except OSError as e:
        return CheckedProgram((f"{path}: {e.strerror}",))
    except UnicodeDecodeError as e:
        return CheckedProgram((f"{path}: not UTF-8 text: {e.reason}",))
    try:
        compiled = compile_source(source, application_name(path.stem), 1, source=str(path))
    except CellctlError as e:
        return CheckedProgram((str(e),))
    return CheckedProgram(lines=len(source.splitlines()), compiled=compiled)


def _compile(source: str, name: str, origin: str) -> Any:
    from cellctl.kinds.ibm7545.aml import compile_source

    return compile_source(source, application_name(name), 1, source=origin)


def _check_text(function: str, name: str, text: str, options: BaseModel) -> list[str]:
    """A record file a manual function downloads: its problem, if it does not parse."""
    from cellctl.kinds.ibm7545.records import ProgramFile

    try:
        ProgramFile.parse(text, name)
    except UsageError as e:
        return [str(e)]
    return []


def _condition(status: Any) -> Any:
    return robot_condition(status.state, status.machine.ok)


def _menu() -> Sequence[MachineFunction]:
    from cellctl.kinds.ibm7545.menu import MENU

    return MENU


def _commands() -> Sequence[tuple[str, click.Command]]:
    from cellctl.kinds.ibm7545.cli import emulate_robot, robot

    return [("", robot), ("emulate", emulate_robot)]


def _timing() -> Any:
    from cellctl.kinds.ibm7545.motion import ArmModel

    return ArmModel()


IBM7545 = MachineKind(
    name="ibm7545",
    family="robot",
    maker="IBM",
    model="7545 Manufacturing System",
    line="4800,7E2",
    options=RobotConfig,
    open_driver=_open,
    emulator=_emulator,
    states=RobotState,
    condition=_condition,
    language=ProgramLanguage(suffix=".aml", check=_check, compile=_compile),
    menu=_menu,
    commands=_commands,
    command_names=(("", "robot"), ("emulate", "robot")),
    program_files=(".rec",),
    check_text=_check_text,
    faults=LazyTable("cellctl.kinds.ibm7545.emulator:FAULTS"),
    timing=_timing,
    description="SCARA robot controller: records over a 4800 baud line, AML/E programs",
)
#: The 7547: the same controller, line and programs (its own name in cell.toml and OPC UA).
IBM7547 = dataclasses.replace(
    IBM7545, name="ibm7547", model="7547 Manufacturing System", commands=None
)
