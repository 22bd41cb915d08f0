"""``cellctl mill``: drive a Dyna 2400 mill from the shell; ``cellctl emulate mill``: serve one.

``cellctl mill [--link URL | NAME] COMMAND``; outcomes are printed in the source's words,
failures as one line on stderr with a non-zero exit code. ``check`` and ``preview`` need no
link: they read the machine's travel from ``cell.toml`` when a NAME is given.
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import click
from rich.progress import BarColumn, TextColumn

from cellctl.clock import current_clock
from cellctl.errors import UsageError, with_article
from cellctl.files import write_output
from cellctl.kinds.dyna2400.dynalan import ProgramRole, Severity, ValidationContext, parse_program
from cellctl.kinds.dyna2400.dynalan import validate as validate_program
from cellctl.kinds.dyna2400.emulator import OperatorDelays
from cellctl.kinds.dyna2400.options import MillConfig
from cellctl.kinds.families import estimated_done
from cellctl.service.machines import load_cell_file
from cellctl.ui.calls import LazyBar, machine_call, read_program
from cellctl.ui.common import (
    MachineGroup,
    cell_dir,
    console,
    err_console,
    fault_help,
    kind_option,
    run,
)
from cellctl.ui.emulate_cli import listen_options, serve_until_stopped, switch_faults


def _call(ctx: click.Context, function: str, **params: Any) -> dict[str, Any]:
    """Run a mill function (see :func:`cellctl.ui.calls.machine_call`); print its outcome."""
    result = machine_call(ctx, "mill", function, params)
    _print(result)
    return result


def _print(result: dict[str, Any]) -> None:
    for line in result.get("lines", []):
        console.print(line, markup=False)
    if "lines" not in result or result["lines"] == []:
        console.print(result["message"], markup=False)
    for line in result.get("after", []):
        console.print(line, markup=False)


def _offline_config(ctx: click.Context) -> MillConfig:
    """The named machine's config from cell.toml (travel ...), without opening its link."""
    name = ctx.meta.get("machine_name")
    other = (ctx.find_object(dict) or {}).get("kind")
    if other not in (None, "dyna2400"):
        raise UsageError(
            f"--kind {other}: `mill check` and `mill preview` read DYNALAN, the dyna2400's; "
            "any kind's program: `cellctl program check|preview FILE`"
        )
    if name is None:
        return MillConfig()
    machines = load_cell_file(cell_dir(ctx)).get("machines", {})
    entry = machines.get(name)
    if not isinstance(entry, dict):
        raise UsageError(f"unknown mill {name!r}")
    if entry.get("kind") != "dyna2400":
        raise UsageError(
            f"{name} is {with_article(str(entry.get('kind')))}: `mill check` reads DYNALAN; its "
            f"programs: `cellctl program check --machine {name} FILE`"
        )
    return MillConfig.from_options(dict(entry.get("options", {})))


def _program_file(path: Path) -> Path:
    if not path.exists():  # a directory or a device: the program's check says what it is
        raise click.BadParameter(f"{path}: file not found", param_hint="PROGRAM")
    return path


@click.group(cls=MachineGroup)
@click.option("--link", metavar="URL", help="Device path, socket://, rfc2217:// or loop://.")
@click.option(
    "--line", metavar="SETTINGS", help="Line settings, e.g. 4800,7E2 (the kind's by default)."
)
@click.option(
    "--trace", type=click.Path(dir_okay=False), help="Write every byte both ways to this file."
)
@click.option(
    "--readiness",
    type=click.Choice(["modem", "inband"]),
    help="Where readiness comes from: CTS (modem, the default) or DC1/DC3 in the data (inband, "
    "for links without modem lines).",
)
@kind_option("mill")
@click.pass_context
def mill(
    ctx: click.Context,
    link: str | None,
    line: str | None,
    trace: str | None,
    readiness: str | None,
    kind: str | None,
) -> None:
    """A mill: the cell's NAME, or the one at --link URL: [--link URL [--kind KIND] | NAME]
    COMMAND.

    The commands are the Dyna 2400's, then those other mill kinds add (each says its kind).
    """
    ctx.obj = {"link": link, "line": line, "trace": trace, "readiness": readiness, "kind": kind}


@mill.command(
    help="INITIALIZE with the SETUP program; then jog to the reference zero and press NEXT. "
    f"An emulator's operator does both by itself {OperatorDelays().setup:g} s of machine time "
    "after the setup (divided by its --time-scale; never with its fault no-next)."
)
@click.argument("setup", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--force", is_flag=True, help="Initialize even if already initialized (failure).")
@click.pass_context
def init(ctx: click.Context, setup: Path, force: bool) -> None:
    _call(ctx, "init", force=force, **read_program(setup))


def _clock(seconds: float) -> str:
    s = max(0, round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def _progress_columns() -> tuple[Any, ...]:
    return (
        TextColumn("[bold]block {task.fields[block]}/{task.fields[blocks]}"),
        BarColumn(),
        TextColumn("{task.fields[lines]}/{task.fields[lines_total]} lines"),
        TextColumn("{task.fields[bytes_sent]}/{task.fields[bytes_total]} B"),
        TextColumn("{task.fields[rate]:>6.1f} chars/s"),
        TextColumn("{task.fields[phase]}"),
        TextColumn("{task.fields[left]}"),
    )


@mill.command()
@click.argument("program", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--no-wait", is_flag=True, help="Return once the last block is taken (state 3).")
@click.option(
    "--time-scale",
    type=click.FloatRange(min=0, min_open=True, max=100_000),
    help="The machine's time scale, for an emulator run with --time-scale: the progress and "
    "time left divide the program's cut estimate by it (a cell's mill: its cell.toml "
    "option time_scale, 1 for a real mill).",
)
@click.pass_context
def download(ctx: click.Context, program: Path, no_wait: bool, time_scale: float | None) -> None:
    """DOWNLOAD: validate, split into blocks, stream them as the controller asks; the bar and
    the time left follow the program's estimate (line time and cut), corrected by the mill."""
    text = read_program(program)
    # The time since a report belongs to that report's phase: a block's characters are on
    # the wire after the write that reported them (writes run ahead), up to the next report.
    sending: dict[str, Any] = {"time": 0.0, "mark": 0.0, "phase": None}

    def fields(p: dict[str, Any], elapsed: float) -> dict[str, Any]:
        if sending["phase"] == "sending":
            sending["time"] += elapsed - sending["mark"]
        sending["mark"] = elapsed
        sending["phase"] = p["phase"]
        # The bar and the time left follow the run's estimate (line time and the program's
        # cut time), corrected by the mill's reports: it moves through the cut too.
        done = estimated_done(p, current_clock().now())
        total = float(p.get("estimate_s") or 0.0)
        left = "" if done is None else f"{_clock(total - done)} left"
        return {
            "total": p["bytes_total"] if done is None else total,
            "completed": p["bytes_sent"] if done is None else done,
            "left": left,
            "bytes_sent": p["bytes_sent"],
            "bytes_total": p["bytes_total"],
            "block": p["block"],
            "blocks": p["blocks"],
            "lines": p["lines"],
            "lines_total": p["lines_total"],
            "rate": p["bytes_sent"] / sending["time"] if sending["time"] > 0 else 0.0,
            "phase": p["phase"],
        }

    with LazyBar(_progress_columns(), program.name, fields, tick=0.5) as bar:
        options = {"time_scale": time_scale} if time_scale is not None else None
        result = machine_call(
            ctx, "mill", "download", {"wait": not no_wait, **text}, bar.update, options=options
        )
    _print(result)


@mill.command()
@click.argument("program", type=click.Path(dir_okay=False, path_type=Path))
@click.pass_context
def load(ctx: click.Context, program: Path) -> None:
    """PROGRAM LOAD (at most 900 lines), to start later with GO."""
    _call(ctx, "load", **read_program(program))


@mill.command()
@click.option(
    "--start-signal",
    metavar="COIL",
    help="PLC coil wired to the controller's start input (default: the mill's go_output).",
)
@click.pass_context
def go(ctx: click.Context, start_signal: str | None) -> None:
    """GO: start the loaded program by pulsing the PLC coil wired to the start input."""
    options = {"go_output": start_signal} if start_signal else None
    _print(machine_call(ctx, "mill", "go", {}, options=options))


@mill.command()
@click.pass_context
def end(ctx: click.Context) -> None:
    """ENDLOAD / HALT: the END program; the controller returns to manual (state 0)."""
    _call(ctx, "end")


@mill.command()
@click.pass_context
def status(ctx: click.Context) -> None:
    """STATUS: state 0-4, "reference zero not set" / "executing", CTS."""
    _call(ctx, "status")


@mill.command()
@click.argument("file", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--timeout", type=float, default=120.0, show_default=True, help="Seconds to wait.")
@click.pass_context
def upload(ctx: click.Context, file: Path | None, timeout: float) -> None:
    """Receive the controller's program (start UPLOAD on its panel); to FILE or stdout."""
    err_console.print("waiting for the controller: select UPLOAD on its panel")
    text = machine_call(ctx, "mill", "upload", {"timeout": timeout})["text"]
    if file is None:
        sys.stdout.write(text)
    else:
        try:
            write_output(file, text)
        except OSError as e:
            raise UsageError(f"{file}: cannot write: {e.strerror}") from None
        console.print(f"{len(text.splitlines())} lines written to {file}")


@mill.command()
@click.argument("program", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--role",
    type=click.Choice([r.value for r in ProgramRole]),
    default="auto",
    show_default=True,
    help="Rules to apply: setup, milling or end program.",
)
@click.pass_context
def check(ctx: click.Context, program: Path, role: str) -> None:
    """Validate PROGRAM like a linter: every problem, exit 1 on errors."""
    _program_file(program)
    config = _offline_config(ctx)
    parsed = parse_program(read_program(program)["text"], name=program.name)
    context = ValidationContext(role=ProgramRole(role), config=config.machine())
    result = validate_program(parsed, context)
    for problem in result.problems:
        colour = "red" if problem.severity is Severity.ERROR else "yellow"
        console.print(problem.format(str(program)), style=colour, markup=False, soft_wrap=True)
    summary = f"{len(result.errors)} error(s), {len(result.warnings)} warning(s)"
    if result.ok and result.blocks is not None and result.toolpath is not None:
        minutes = result.toolpath.machining_seconds / 60
        summary += f"; {len(result.blocks)} block(s), est. {minutes:.1f} min machining"
    console.print(summary)
    if not result.ok:
        sys.exit(1)


@mill.command()
@click.argument("program", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Where to draw it: .svg or .png.",
)
@click.pass_context
def preview(ctx: click.Context, program: Path, output: Path) -> None:
    """Draw PROGRAM's toolpath (XY view, Z profile, block boundaries) to an SVG or PNG."""
    from cellctl.kinds.dyna2400.preview import render_png, render_svg

    _program_file(program)
    suffix = output.suffix.lower()
    if suffix not in (".svg", ".png"):
        raise click.BadParameter("the output must end in .svg or .png", param_hint="-o")
    config = _offline_config(ctx)
    parsed = parse_program(read_program(program)["text"], name=program.name)
    result = validate_program(parsed, ValidationContext(config=config.machine()))
    if result.toolpath is None:
        first = result.errors[0].format(str(program)) if result.errors else "no toolpath"
        err_console.print(f"error: cannot trace {program}: {first}", markup=False)
        sys.exit(1)
    try:
        if suffix == ".svg":
            write_output(output, render_svg(result.toolpath, title=program.name))
        else:
            write_output(output, render_png(result.toolpath, title=program.name))
    except OSError as e:
        raise UsageError(f"{output}: cannot write: {e.strerror}") from None
    path = result.toolpath
    console.print(
        f"{output}: {path.blocks} block(s), {len(path.moves)} moves, "
        f"est. {path.machining_seconds / 60:.1f} min machining"
    )
    for problem in result.errors:
        err_console.print(problem.format(str(program)), markup=False)
    if result.errors:
        sys.exit(1)  # drawn as far as it goes, but the program has errors, as `check` says


# -- cellctl emulate mill ------------------------------------------------------------------------

_PANEL_HELP = (
    "panel keys: power, off, clear, select execute|line|load|upload|manual, jog, next, start, show"
)


async def _panel(device: Any) -> None:
    """Manual mode: operator keys from stdin, one a line."""
    from cellctl.kinds.dyna2400.emulator import LinkMode

    modes = {
        "execute": LinkMode.PROGRAM_EXECUTE,
        "line": LinkMode.LINE_EXECUTE,
        "load": LinkMode.PROGRAM_LOAD,
        "upload": LinkMode.UPLOAD,
        "manual": LinkMode.MANUAL,
    }
    console.print(_PANEL_HELP)
    while True:
        text = await asyncio.to_thread(sys.stdin.readline)
        if not text:
            return
        words = text.split()
        if not words:
            continue
        try:
            if words[0] == "power":
                device.power_on()
            elif words[0] == "off":
                device.power_off()
            elif words[0] == "clear":
                device.clear_memory()
            elif words[0] == "select" and len(words) == 2 and words[1] in modes:
                device.select(modes[words[1]])
            elif words[0] == "jog":
                device.jog_to_reference()
            elif words[0] == "next":
                device.press_next()
            elif words[0] == "start":
                device.cycle_start()
            elif words[0] != "show":
                console.print(_PANEL_HELP)
                continue
        except UsageError as e:
            console.print(f"panel: {e}")
        cts = "high" if device.rts else "low"
        console.print(f"display: {device.display}  (RTS {cts}, {len(device.memory)} lines)")


def _carries_modem_lines(listen: str) -> bool:
    """True for an emulator's ``--listen`` whose links carry the modem lines (RTS/CTS):
    ``rfc2217://`` only; a pty and ``socket://`` carry the data alone."""
    return urlsplit(listen).scheme == "rfc2217"


def _emulator_readiness(listen: str, readiness: str | None) -> str:
    """The emulator's readiness: the one given, else the one its ``listen`` can carry
    (``modem`` over RFC 2217, ``inband`` on a pty or raw TCP). ``modem`` where no modem line
    goes is refused: no driver could see the mill ready."""
    if readiness is None:
        return "modem" if _carries_modem_lines(listen) else "inband"
    if readiness == "modem" and not _carries_modem_lines(listen):
        raise UsageError(
            f"--readiness modem: the mill would say it is ready on RTS alone, which --listen "
            f"{listen} cannot carry (no modem lines: no driver would see it ready); use "
            "--listen rfc2217://127.0.0.1:0, or --readiness inband"
        )
    return readiness


def _drive_hint(readiness: str, line: str) -> str:
    """What ``cellctl emulate mill`` says to drive it with: ``cellctl mill --link {url}``
    and the options this emulator needs of the driver (in-band readiness, its line when not
    the mill's usual), so that the command works as printed."""
    from cellctl.link import MILL_LINE, LineSettings

    command = "cellctl mill --link {url}"
    if readiness == "inband":
        command += " --readiness inband"
    settings = LineSettings.parse(line)
    if str(settings) != str(MILL_LINE):
        command += f" --line {settings}"
    return f"drive it with: {command}"


def _emulate_mill_command() -> click.Command:
    from cellctl.kinds.dyna2400.emulator import FAULTS, Dyna2400Emulator, LinkMode, OperatorDelays
    from cellctl.link import MILL_LINE

    def callback(
        listen: str,
        time_scale: float,
        no_pacing: bool,
        line: str,
        fault: tuple[str, ...],
        readiness: str | None,
        manual: bool,
        setup_delay: float,
    ) -> None:
        readiness = _emulator_readiness(listen, readiness)
        hint = _drive_hint(readiness, line)

        async def main() -> None:
            device = Dyna2400Emulator(
                time_scale=time_scale,
                automatic=not manual,
                readiness=readiness,
                delays=OperatorDelays(setup=setup_delay),
                mode=LinkMode.PROGRAM_EXECUTE,
            )
            said = switch_faults(device, FAULTS, fault)
            device.start()
            panel = asyncio.ensure_future(_panel(device)) if manual else None
            try:
                await serve_until_stopped(
                    device,
                    listen,
                    line,
                    not no_pacing,
                    "Dyna 2400 mill emulator",
                    hint,
                    said,
                )
            finally:
                if panel is not None:
                    panel.cancel()

        run(main)

    params = [
        *listen_options(MILL_LINE, FAULTS),
        click.Option(
            ["--readiness"],
            type=click.Choice(["modem", "inband"]),
            help="Where it says it is ready: modem (RTS, the host's CTS), or inband (also "
            "DC1/DC3 in the data when RTS changes). Default: modem over rfc2217://, inband on "
            "a pty or socket://, which carry no modem lines.",
        ),
        click.Option(["--manual"], is_flag=True, help="Play the operator yourself (stdin)."),
        click.Option(
            ["--setup-delay"],
            type=float,
            default=20.0,
            show_default=True,
            help="Machine seconds the automatic operator takes to set the reference zero.",
        ),
    ]
    return click.Command(
        "mill",
        callback=callback,
        params=params,
        help="Emulate a Dyna 2400 CNC mill controller.\n\n" + fault_help(FAULTS),
    )


emulate_mill = _emulate_mill_command()
