"""``cellctl robot``: drive an IBM 7545/7547 controller from the shell.

``cellctl robot [--link URL | NAME] COMMAND``; every outcome is printed in the source's
words, failures as one line on stderr with a non-zero exit code.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    TextColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from cellctl.errors import CellctlError, UsageError
from cellctl.files import write_output
from cellctl.link import ROBOT_LINE
from cellctl.ui.calls import LazyBar, machine_call, read_program
from cellctl.ui.common import MachineGroup, console, fault_help, kind_option, run


def _call(ctx: click.Context, function: str, **params: Any) -> dict[str, Any]:
    """Run a robot function (see :func:`cellctl.ui.calls.machine_call`) and print its outcome
    in the source's words."""
    result = machine_call(ctx, "robot", function, params)
    _print(result)
    return result


def _print(result: dict[str, Any]) -> None:
    for line in result.get("lines", []):
        console.print(line, markup=False)
    console.print(result["message"], markup=False)


#: What ``cellctl emulate robot`` says to drive its emulator with.
HINT = "drive it with: cellctl robot --link {url}"


@click.group(cls=MachineGroup)
@click.option("--link", metavar="URL", help="Device path, socket://, rfc2217:// or loop://.")
@click.option(
    "--line", metavar="SETTINGS", help="Line settings, e.g. 4800,7E2 (the kind's by default)."
)
@click.option(
    "--trace", type=click.Path(dir_okay=False), help="Write every byte both ways to this file."
)
@kind_option("robot")
@click.pass_context
def robot(
    ctx: click.Context, link: str | None, line: str | None, trace: str | None, kind: str | None
) -> None:
    """A robot: the cell's NAME, or the one at --link URL: [--link URL [--kind KIND] | NAME]
    COMMAND.

    The commands are the IBM 7545/7547 controller's, then those other robot kinds add (each
    says its kind). While `cellctl run` runs the cell, a command on one of its machines goes
    through the controller's API (the machine must be out of automatic service for anything
    but status).
    """
    ctx.obj = {"link": link, "line": line, "trace": trace, "kind": kind}


@robot.command()
@click.pass_context
def init(ctx: click.Context) -> None:
    """Return home, then auto mode (robot state 1)."""
    _call(ctx, "init")


def _download_fields(data: dict[str, Any], elapsed: float) -> dict[str, Any]:
    return {
        "completed": data["records"],
        "total": data["records_total"],
        "sent": data["bytes_sent"],
        "rate": data["bytes_sent"] / max(elapsed, 1e-6),
        "retry": f"retry {data['retry']}" if data.get("retry") else "",
    }


@robot.command()
@click.argument("partition", type=int)
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
@click.pass_context
def download(ctx: click.Context, partition: int, file: Path) -> None:
    """Download a compiled program file (.rec) into PARTITION 1-5; an AML source (.aml) is
    compiled on the way, as the console does."""
    if not 1 <= partition <= 5:
        raise click.BadParameter("partition must be 1 to 5 (partition error)")
    program = _as_sent(file, partition, read_program(file))
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("records  {task.fields[sent]} B"),
        TextColumn("{task.fields[rate]:>6.1f} chars/s"),
        TimeRemainingColumn(),
        TextColumn("[yellow]{task.fields[retry]}"),
    )
    with LazyBar(columns, f"{file.name} -> partition {partition}", _download_fields) as bar:
        result = machine_call(
            ctx, "robot", "download", {"partition": partition, **program}, bar.update
        )
    _print(result)


def _application(stem: str) -> str:
    """The application name a program is compiled with by default: its file's stem, in
    capitals, without '-' and '_', at most 8 characters."""
    return stem.upper().replace("-", "").replace("_", "")[:8]


def _as_sent(file: Path, partition: int, program: dict[str, str]) -> dict[str, str]:
    """The program ``download`` sends: a .aml source compiled on the way (the console's
    picker does so too: the same file is taken the same way everywhere); a file that is no
    record file but AML source refused with what to do (compile it, or name it .aml)."""
    from cellctl.kinds.ibm7545.aml import compile_source
    from cellctl.kinds.ibm7545.records import ProgramFile

    text = program["text"]
    if file.suffix.lower() == ".aml":
        compiled = compile_source(text, _application(file.stem), partition, source=str(file))
        click.echo(
            f"{file}: AML source, compiled on the way ({len(compiled.body)} instructions, name "
            f"{_application(file.stem)}); `cellctl robot compile {file}` keeps the .rec",
            err=True,
        )
        return {"program": file.stem + ".rec", "text": compiled.to_text()}
    try:
        ProgramFile.parse(text, source=str(file))
    except UsageError as e:
        if "not a record" not in str(e) or not _is_aml(text, str(file)):
            return program  # refused where every download is checked, in its words
        raise UsageError(
            f"{e}: {file} looks like AML source: compile it first (cellctl robot compile "
            f"{file} -o {file.with_suffix('.rec')}), or name it .aml and download compiles it "
            "on the way"
        ) from None
    return program


def _is_aml(text: str, source: str) -> bool:
    """Whether ``text`` compiles as AML/E source."""
    from cellctl.kinds.ibm7545.aml import compile_program

    try:
        compile_program(text, source)
    except CellctlError:
        return False
    return True


@robot.command()
@click.argument("partition", type=int)
@click.pass_context
def go(ctx: click.Context, partition: int) -> None:
    """Run the program in PARTITION 1-5 (select application, start cycle)."""
    if not 1 <= partition <= 5:
        raise click.BadParameter("partition must be 1 to 5 (starting function error)")
    _call(ctx, "go", partition=partition)


@robot.command()
@click.pass_context
def stop(ctx: click.Context) -> None:
    """Stop the cycle (robot state 1)."""
    _call(ctx, "stop")


@robot.command()
@click.pass_context
def halt(ctx: click.Context) -> None:
    """Stop the cycle and treat the robot as uninitialized (partitions flushed)."""
    _call(ctx, "halt")


@robot.command()
@click.pass_context
def status(ctx: click.Context) -> None:
    """Robot state, decoded status bytes, partitions Full/Empty (another kind: its own)."""
    st = machine_call(ctx, "robot", "status", {})
    if "partitions" not in st:  # another robot kind's status: its own words
        _print(st)
        return
    table = Table(title=st["name"], show_header=False)
    table.add_row("Robot state", f"{st['state']} ({st['state_text']})")
    table.add_row("Machine status", f"{st['machine_status']} (bytes {st['status_bytes']})")
    for p, prog in st["partitions"].items():
        table.add_row(f"Partition {p}", f"Full ({prog})" if prog else "Empty")
    console.print(table)
    # An executing program blocked in WAITI with nothing to drive its input: say so.
    for line in st["lines"]:
        if line.startswith(("waiting:", "  without one:")):
            console.print(line, markup=False, highlight=False)


@robot.command()
@click.pass_context
def reject(ctx: click.Context) -> None:
    """The reject status: why the controller last refused a request."""
    _call(ctx, "reject")


@robot.group(invoke_without_command=True)
@click.pass_context
def io(ctx: click.Context) -> None:
    """The 16 digital inputs and 16 outputs; `io set N on|off` drives an emulator's input."""
    if ctx.invoked_subcommand is not None:
        return
    dido = machine_call(ctx, "robot", "io", {})
    table = Table(title=f"{dido['name']} DI/DO")
    table.add_column("line", justify="right")
    for n in range(1, 17):
        table.add_column(str(n), justify="center")
    table.add_row("DI", *("1" if x else "." for x in dido["inputs"]))
    table.add_row("DO", *("1" if x else "." for x in dido["outputs"]))
    console.print(table)


@io.command("set")
@click.argument("line", type=click.IntRange(1, 16), metavar="N")
@click.argument("value", type=click.Choice(["on", "off"]))
@click.pass_context
def io_set(ctx: click.Context, line: int, value: str) -> None:
    """Drive input N (1-16) on or off: for an emulator with no PLC behind it (a program in
    WAITI goes on); a real robot refuses, its inputs come from its wiring."""
    _call(ctx, "io_set", input=line, on=value == "on")


@robot.command()
@click.pass_context
def reset(ctx: click.Context) -> None:
    """Error reset (ERRESET): clear machine-status and reject-status errors."""
    _call(ctx, "reset")


@robot.command()
@click.pass_context
def home(ctx: click.Context) -> None:
    """Return the arm home."""
    _call(ctx, "home")


@robot.command()
@click.argument("source", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "-o", "--output", type=click.Path(dir_okay=False, path_type=Path), help="Program file."
)
@click.option(
    "--partition",
    type=click.IntRange(1, 5),
    default=1,
    show_default=True,
    help="Robot memory partition the program is for.",
)
@click.option("--name", help="Application name (8 characters; default: the file's stem).")
def compile(source: Path, output: Path | None, partition: int, name: str | None) -> None:
    """Compile an AML/E source file into a program file of records (.rec)."""
    from cellctl.kinds.ibm7545.aml import compile_source

    def main() -> None:
        text = read_program(source)["text"]
        app = _application(name or source.stem)
        program = compile_source(text, app, partition, source=str(source))
        target = output or source.with_suffix(".rec")
        try:
            write_output(target, program.to_text(), encoding="ascii")
        except OSError as e:
            raise UsageError(f"{target}: cannot write: {e.strerror}") from None
        console.print(f"{source} -> {target}: {len(program.body)} instructions, name {app}")

    async def amain() -> None:
        main()

    run(amain)


def _tell_wait(port: int, value: bool) -> None:
    """What an emulated robot with no PLC behind it waits for, and how to go on."""
    word = "on" if value else "off"
    console.print(
        f"robot: the program waits in WAITI({port}, {int(value)}) for input {port} {word}; "
        f"no PLC drives it here: `cellctl robot --link URL io set {port} {word}` goes on, "
        "`cellctl robot --link URL stop` ends the cycle",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )


def _emulate_command() -> click.Command:
    from cellctl.kinds.ibm7545.emulator import FAULTS, Ibm7545Emulator
    from cellctl.ui.emulate_cli import (
        fleet_options,
        listen_options,
        serve_fleet_until_stopped,
        serve_until_stopped,
        switch_faults,
    )

    def callback(
        listen: str,
        time_scale: float,
        no_pacing: bool,
        line: str,
        fault: tuple[str, ...],
        count: int,
        workers: int,
    ) -> None:
        def make(index: int = 0) -> Ibm7545Emulator:
            device = Ibm7545Emulator(time_scale=time_scale)
            switch_faults(device, FAULTS, fault)
            device.wait_hooks.append(_tell_wait)
            return device

        async def main() -> None:
            what = "IBM 7545 emulator"
            # Every machine takes the same switches: checked (a bad one refused before any
            # machine is served, here rather than in a fleet's worker) and said once.
            said = switch_faults(Ibm7545Emulator(time_scale=time_scale), FAULTS, fault)
            if count == 1 and workers == 1:
                await serve_until_stopped(make(), listen, line, not no_pacing, what, HINT, said)
            else:
                await serve_fleet_until_stopped(
                    make, listen, line, not no_pacing, what, count, workers, HINT, said
                )

        run(main)

    return click.Command(
        "robot",
        callback=callback,
        params=[*listen_options(ROBOT_LINE, FAULTS), *fleet_options()],
        help="Emulate an IBM 7545/7547 robot controller (or --count of them).\n\n"
        + fault_help(FAULTS),
    )


#: ``cellctl emulate robot``.
emulate_robot = _emulate_command()
