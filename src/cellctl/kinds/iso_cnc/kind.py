"""The iso-cnc kind declared for the registry (entry point ``iso-cnc`` in
``cellctl.machine_kinds``): CNC controls fed ISO-code G-code over RS-232 with DC1-DC4 (Fanuc,
Haas style), of the mill family."""

from __future__ import annotations

import contextlib
import errno
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

from cellctl.emulators.serve import scaled_deadline
from cellctl.errors import UsageError
from cellctl.files import read_text
from cellctl.kinds.iso_cnc import gcode, motion, tape
from cellctl.kinds.iso_cnc.options import ISO_LINE, IsoCncOptions, read_capped
from cellctl.kinds.iso_cnc.status import IsoCncState
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
    from cellctl.kinds.iso_cnc.driver import IsoCncDriver

# The driver and the emulator are imported by the hooks that use them: the registry reads
# this declaration at every start (`cellctl --help` too).

#: File endings of G-code programs a shop keeps.
SUFFIXES = (".nc", ".tap", ".gcode", ".ngc", ".cnc")


def _options(options: BaseModel) -> IsoCncOptions:
    return options if isinstance(options, IsoCncOptions) else IsoCncOptions()


async def _open(spec: DriverSpec) -> IsoCncDriver:
    from cellctl.kinds.iso_cnc.driver import IsoCncDriver

    return await IsoCncDriver.connect(
        spec.url,
        name=spec.name,
        settings=spec.settings,
        store=spec.store,
        options=_options(spec.options),
        start_output=spec.start_output,
        trace=spec.trace,
        clock=spec.clock,
    )


def _emulator(spec: EmulatorSpec) -> EmulatedDevice:
    """For the emulated cell: in RMT, CYCLE START from the cell's GO (and, with an
    operator, pressed again whenever it is idle)."""
    from cellctl.kinds.iso_cnc.emulator import EmulatorOptions, IsoCncEmulator, Mode

    known = set(EmulatorOptions.model_fields)
    options = EmulatorOptions(
        **{"auto_operator": spec.operator, **{k: v for k, v in spec.extra.items() if k in known}}
    )
    control = IsoCncEmulator(options, clock=spec.emulator_clock())
    control.mode = Mode.RMT
    return control


def check_text(text: str, name: str, options: BaseModel) -> CheckedProgram:
    """A program's text: its errors (each ``name:line:column: ...``), blocks and run time."""
    chosen = _options(options)
    found = gcode.check(text, chosen.check_options(drip=False))
    problems = tuple(f.format(name) for f in found if f.error)
    if problems:
        # A check that stopped ends with its note, no problem itself: counted apart.
        stopped = any(f.unlisted is not None for f in found)
        tally = gcode.counted(found) if stopped else ""
        return CheckedProgram(problems, lines=text.count("\n"), tally=tally)
    times = motion.block_seconds(
        gcode.iter_blocks(text, chosen.check_options(drip=False)), chosen.motion()
    )
    return CheckedProgram((), lines=len(times), machining_s=math.fsum(times))


def _check(path: Path, role: ProgramRole, options: BaseModel) -> CheckedProgram:
    del role  # a setup program is a program like any other here
    chosen = _options(options).check_options(drip=False)
    try:
        # Over what the check takes: refused before it is read into memory.
        data = read_capped(path, chosen.max_bytes)
    except OSError as e:
        if e.errno == errno.EFBIG:
            with contextlib.suppress(OSError):  # gone since: said as any other failed read
                size = path.stat().st_size
                return CheckedProgram((gcode.too_long(size, chosen).format(str(path)),))
        return CheckedProgram((f"{path}: cannot read: {e.strerror or e}",))
    refusal = tape.not_iso_code(str(path), data)  # in the words `cellctl dnc send` uses
    if refusal is not None:
        return CheckedProgram((refusal,))
    return check_text(data.decode("ascii"), str(path), options)


def _check_text(function: str, name: str, text: str, options: BaseModel) -> list[str]:
    del function
    return list(check_text(text, name, options).problems)


def _split(text: str) -> list[str]:
    return [p.text for p in tape.split_programs(text)]


def _preview(text: str, name: str, options: BaseModel) -> Preview:
    from cellctl.kinds.iso_cnc.preview import render_svg

    chosen = _options(options)
    machine = motion.Machine(chosen.motion())
    steps = (machine.step(b) for b in gcode.iter_blocks(text, chosen.check_options(drip=False)))
    svg, drawn, blocks = render_svg(steps, title=name)
    if not drawn:
        raise UsageError(f"cannot trace {Path(name).stem}: no moves")
    return Preview(svg, blocks)


def _emulated_options(scale: float) -> dict[str, float]:
    # A line made `scale` times faster carries `scale` times more characters in one
    # millisecond of this process's scheduling: small bursts and a wide margin keep the
    # emulated control's buffer clear of its high-water mark all the same.
    return {
        "pace_s": 0,
        "margin": 128,
        "motion_scale": scale,
        "dc1_timeout": scaled_deadline(120.0, scale),
        "end_extra": scaled_deadline(60.0, scale),
        "setup_timeout": scaled_deadline(1800.0, scale),
    }


class CutModel:
    """The mill family's timing model (:class:`cellctl.kinds.families.MillModel`): each
    program's run time by the motion model, and its characters on the line."""

    def __init__(self, options: IsoCncOptions | None = None) -> None:
        self.options = options or IsoCncOptions()

    def cut_times(self, setup: Path | None, programs: Sequence[Path]) -> list[tuple[float, int]]:
        del setup
        out = []
        for path in programs:
            text = read_text(path, "ascii")
            blocks = gcode.iter_blocks(text)
            framed = tape.frame(text, leader=self.options.leader, trailer=self.options.trailer)
            out.append((motion.program_seconds(blocks, self.options.motion()), len(framed)))
        return out


def _timing() -> Any:
    return CutModel()


def _condition(status: Any) -> Any:
    return status.kind_condition


def _menu() -> Sequence[Any]:
    from cellctl.kinds.iso_cnc.menu import MENU

    return MENU


def _commands() -> Sequence[tuple[str, click.Command]]:
    from cellctl.kinds.iso_cnc.cli import emulate_iso_cnc
    from cellctl.kinds.iso_cnc.dnc.cli import dnc

    return [("emulate", emulate_iso_cnc), ("", dnc)]


ISO_CNC = MachineKind(
    name="iso-cnc",
    family="mill",
    maker="ISO-code",
    model="CNC control (Fanuc/Haas style RS-232)",
    line=ISO_LINE,
    options=IsoCncOptions,
    open_driver=_open,
    emulator=_emulator,
    states=IsoCncState,
    condition=_condition,
    language=ProgramLanguage(suffix=".nc", check=_check, split=_split, preview=_preview),
    commands=_commands,
    command_names=(("emulate", "iso-cnc"), ("", "dnc")),
    menu=_menu,
    timing=_timing,
    emulated_options=_emulated_options,
    needs_setup=False,
    program_files=SUFFIXES,
    check_text=_check_text,
    faults=LazyTable("cellctl.kinds.iso_cnc.emulator:FAULTS"),
    description="CNC control fed ISO-code G-code over RS-232 with DC1-DC4 (read-in, "
    "drip-feed, punch)",
)
