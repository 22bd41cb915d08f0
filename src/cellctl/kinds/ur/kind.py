"""Universal Robots (CB3, e-Series), declared for the registry (entry point ``ur`` in
``cellctl.machine_kinds``): everything cellctl knows of a UR, found by the registry only."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

from cellctl.emulators.serve import scaled_deadline
from cellctl.errors import CellctlError, UsageError
from cellctl.files import read_text
from cellctl.kinds.kind import (
    CheckedProgram,
    DriverSpec,
    EmulatorSpec,
    LazyTable,
    MachineKind,
    MachineState,
    Preview,
    ProgramLanguage,
    ProgramRole,
)
from cellctl.kinds.ur.dashboard import RobotMode
from cellctl.kinds.ur.options import UR_LINE, UrOptions

if TYPE_CHECKING:
    import click

    from cellctl.emulators.serve import EmulatedDevice
    from cellctl.kinds.menu import MachineFunction
    from cellctl.kinds.ur.driver import UrRobot

# The driver, the emulator and the URScript tools are imported by the hooks that use them:
# the registry reads this declaration at every start (`cellctl --help` too).


#: The robot modes as the kind declares its states (numbers and UR's names, from the codec's
#: one table).
UrRobotMode: type[MachineState] = MachineState(  # type: ignore[assignment]
    "UrRobotMode",  # type: ignore[arg-type]
    [(m.name, (int(m), m.text)) for m in RobotMode],  # type: ignore[arg-type]
)


async def _open(spec: DriverSpec) -> UrRobot:
    from cellctl.kinds.ur.driver import UrRobot

    assert isinstance(spec.options, UrOptions)
    return await UrRobot.connect(
        spec.url,
        name=spec.name,
        settings=spec.settings,
        store=spec.store,
        options=spec.options,
        trace=spec.trace,
        clock=spec.clock,
    )


def _emulator(spec: EmulatorSpec) -> EmulatedDevice:
    from cellctl.kinds.ur.emulator import UrEmulator

    return UrEmulator(
        clock=spec.emulator_clock(),
        model=str(spec.extra.get("model", "UR5e")),
        programs=dict(spec.extra.get("programs", {})),
    )


def _arm(options: BaseModel) -> Any:
    from cellctl.kinds.ur.motion import ARMS

    return ARMS[options.model if isinstance(options, UrOptions) else UrOptions().model]


def _check(path: Path, role: ProgramRole, options: BaseModel) -> CheckedProgram:
    """A URScript file (or a ``.urp`` reference): its problems with line and column, its
    lines and its run time on the configured model's motion model."""
    from cellctl.kinds.ur.program import compile_program
    from cellctl.kinds.ur.urscript import estimate, parse

    try:
        text = read_text(path)
    except OSError as e:
        return CheckedProgram((f"{path}: cannot read it: {e.strerror or e}",))
    except UnicodeDecodeError as e:
        return CheckedProgram((f"{path}: cannot read it: {e}",))
    arm = _arm(options)
    try:
        program = compile_program(text, path.stem, str(path), arm)
    except CellctlError as e:
        return CheckedProgram(tuple(str(e).split("; ")))
    problems = program.problems(arm)
    if problems or program.on_robot:
        return CheckedProgram(tuple(problems), lines=len(text.splitlines()), compiled=program)
    seconds, _ = estimate(parse(text), arm)
    return CheckedProgram(lines=len(text.splitlines()), machining_s=seconds, compiled=program)


def _compile(source: str, name: str, origin: str) -> Any:
    from cellctl.kinds.ur.program import compile_program

    return compile_program(source, name, origin)


def _preview(text: str, name: str, options: BaseModel) -> Preview:
    from cellctl.kinds.ur.program import preview_svg

    svg, moves = preview_svg(text, name, _arm(options))
    if not moves:
        raise UsageError(f"{name}: no moves to draw")
    return Preview(svg, moves)


def _check_text(function: str, name: str, text: str, options: BaseModel) -> list[str]:
    from cellctl.kinds.ur.program import UrProgram

    return UrProgram(Path(name).stem, name, text).problems(_arm(options))


def _condition(status: Any) -> Any:
    return status.condition


def _menu() -> Sequence[MachineFunction]:
    from cellctl.kinds.ur.menu import MENU

    return MENU


#: The UR's functions the IBM robot's command group does not have, with their help: each is
#: ``cellctl robot NAME`` (the API method's name).
ROBOT_FUNCTIONS = {
    "unlock": "A UR: unlock a protective stop, after inspecting its cause.",
    "close_safety_popup": "A UR: close the pendant's safety popup.",
    "play": "A UR: play (resume) the loaded or paused program.",
    "pause": "A UR: pause the running program.",
    "power_off": "A UR: power the arm off.",
}


def _commands() -> Sequence[tuple[str, click.Command]]:
    from cellctl.kinds.ur.cli import ROBOT_COMMANDS, emulate_ur

    return [("emulate", emulate_ur), *(("robot", command) for command in ROBOT_COMMANDS)]


def _timing() -> Any:
    from cellctl.kinds.ur.timing import UrTiming

    return UrTiming()


def _emulated_options(scale: float) -> dict[str, float]:
    return {
        "power_on_timeout": scaled_deadline(60.0, scale),
        "brake_release_timeout": scaled_deadline(30.0, scale),
    }


UR = MachineKind(
    name="ur",
    family="robot",
    maker="Universal Robots",
    model="UR e-Series cobot",
    line=UR_LINE,
    options=UrOptions,
    open_driver=_open,
    emulator=_emulator,
    states=UrRobotMode,
    condition=_condition,
    language=ProgramLanguage(suffix=".script", check=_check, compile=_compile, preview=_preview),
    menu=_menu,
    commands=_commands,
    command_names=(("emulate", "ur"), *(("robot", name) for name in ROBOT_FUNCTIONS)),
    emulated_options=_emulated_options,
    program_files=(".script", ".urp"),
    check_text=_check_text,
    faults=LazyTable("cellctl.kinds.ur.emulator:FAULTS"),
    timing=_timing,
    description="collaborative arm: Dashboard Server, RTDE and URScript over TCP",
)
