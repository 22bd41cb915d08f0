"""``cellctl emulate iso-cnc``: serve an emulated ISO-code CNC control.

With ``--panel`` the operator's keys are read from stdin, one a line: ``edit``, ``mem``,
``rmt`` (the mode), ``read``, ``start`` (CYCLE START), ``punch [N]``, ``reset``, ``list``.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import click

from cellctl.errors import CellctlError, UsageError
from cellctl.files import read_text, reason
from cellctl.kinds.iso_cnc import tape
from cellctl.kinds.iso_cnc.emulator import FAULTS, EmulatorOptions, IsoCncEmulator, Mode
from cellctl.kinds.iso_cnc.options import ISO_LINE
from cellctl.link import LineSettings
from cellctl.ui.common import console, fault_help, run, stdin_lines
from cellctl.ui.emulate_cli import listen_options, serve_until_stopped, switch_faults


def panel_key(control: IsoCncEmulator, text: str) -> str:
    """One panel key (see module docstring); what the control shows after it."""
    words = text.split()
    key = words[0].lower() if words else ""
    if key in ("edit", "mem", "rmt"):
        control.set_mode(Mode(key.upper()))
    elif key == "read":
        control.read()
    elif key == "start":
        control.cycle_start()
    elif key == "punch":
        control.punch(int(words[1].lstrip("Oo")) if len(words) > 1 else None)
    elif key == "reset":
        control.reset()
    elif key != "list":
        raise UsageError(f"unknown key {key!r}: {PANEL_KEYS}")
    programs = " ".join(f"O{n:04d}" for n in sorted(control.memory)) or "(empty)"
    alarm = f", alarm {control.alarms[-1].code:03d}" if control.activity == "alarm" else ""
    return f"{control.mode} {control.activity}{alarm}; memory: {programs}"


#: The panel's keys, for ``--help`` and the refusal of an unknown one.
PANEL_KEYS = "edit, mem, rmt (the mode), read, start (CYCLE START), punch [N], reset, list"


async def _panel(control: IsoCncEmulator) -> None:
    lines = stdin_lines()
    while True:
        text = await lines.get()
        if not text:
            return
        try:
            console.print(panel_key(control, text), markup=False)
        except (CellctlError, ValueError) as e:
            console.print(f"panel: {e}", markup=False)


@click.option(
    "--mode",
    type=click.Choice([m.value for m in Mode], case_sensitive=False),
    default="EDIT",
    show_default=True,
    help="The mode it starts in.",
)
@click.option(
    "--auto-operator",
    is_flag=True,
    help="Press READ (EDIT) or CYCLE START (RMT) whenever it is idle.",
)
@click.option(
    "--buffer-size", type=int, default=256, show_default=True, help="Its reader buffer, characters."
)
@click.option(
    "--tolerance",
    type=int,
    default=10,
    show_default=True,
    help="Characters it accepts after its DC3.",
)
@click.option("--cs-flow", is_flag=True, help="Also drop RTS (the host's CTS) when full.")
@click.option(
    "--load",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    multiple=True,
    help="A program file put into its memory at power on.",
)
@click.option(
    "--panel",
    is_flag=True,
    help=f"Play the operator: panel keys from stdin, one a line: {PANEL_KEYS}.",
)
def _emulate_iso_cnc(
    listen: str,
    time_scale: float,
    no_pacing: bool,
    line: str,
    fault: tuple[str, ...],
    mode: str,
    auto_operator: bool,
    buffer_size: int,
    tolerance: int,
    cs_flow: bool,
    load: tuple[Path, ...],
    panel: bool,
) -> None:
    LineSettings.parse(line)

    async def main() -> None:
        options = EmulatorOptions(
            buffer_size=buffer_size,
            tolerance=tolerance,
            cs_flow=cs_flow,
            auto_operator=auto_operator,
        )
        control = IsoCncEmulator(options, time_scale=time_scale)
        control.mode = Mode(mode.upper())
        for path in load:
            try:
                text = read_text(path, "ascii")
            except (OSError, UnicodeDecodeError) as e:
                raise UsageError(f"--load {path}: cannot read it: {reason(e)}") from None
            for program in tape.split_programs(text):
                control.memory[program.number] = program.text
        said = switch_faults(control, FAULTS, fault)
        keys = asyncio.ensure_future(_panel(control)) if panel else None
        try:
            await serve_until_stopped(
                control,
                listen,
                line,
                not no_pacing,
                "ISO-code CNC control emulator",
                _dnc_hint(time_scale, line),
                said,
            )
        finally:
            if keys is not None:
                keys.cancel()

    run(main)


def _dnc_hint(time_scale: float, line: str) -> str:
    """What ``cellctl emulate iso-cnc`` says to feed it with: a machine's table of dnc.toml
    (its ``link = "{url}"`` last), with what the DNC driver needs of this emulator to work
    as printed: its line when not the kind's usual, and at a ``time_scale`` other than 1
    ``options.motion_scale`` the same (a drip-feed waits for the modelled end of the motion:
    at scale 1 it would wait the real machine's time)."""
    rows = ["[machines.mill1]"]
    settings = LineSettings.parse(line)
    if str(settings) != str(LineSettings.parse(ISO_LINE)):
        rows.append(f'line = "{settings}"')
    if time_scale != 1:
        # {{ }}: the hint is a format string ({url}).
        rows.append(
            f"options = {{{{ motion_scale = {time_scale:.15g} }}}}"
            "  # its --time-scale: a drip-feed ends as its motion does"
        )
    rows.append('link = "{url}"')
    return "feed it with cellctl dnc (docs/dnc.md), a machine of dnc.toml:" + "".join(
        f"\n      {row}" for row in rows
    )


def _command() -> click.Command:
    """The command: the options every ``emulate`` command takes, then the control's own."""
    command = click.command(
        "iso-cnc",
        help="Emulate an ISO-code CNC control (Fanuc/Haas style RS-232).\n\n" + fault_help(FAULTS),
    )(_emulate_iso_cnc)
    command.params[:0] = listen_options(LineSettings.parse(ISO_LINE), FAULTS)
    return command


emulate_iso_cnc = _command()


__all__ = ["emulate_iso_cnc", "panel_key"]
