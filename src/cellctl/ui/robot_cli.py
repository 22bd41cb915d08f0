"""``cellctl robot``: drive an IBM 7545/7547 controller from the shell.

``cellctl robot [--link URL | NAME] COMMAND``; every outcome is printed in the source's
words, failures as one line on stderr with a non-zero exit code.
"""

from __future__ import annotations

import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import click
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from cellctl.drivers.robot import Ibm7545Robot, RobotConfig
from cellctl.drivers.state import StateStore
from cellctl.errors import UsageError
from cellctl.protocol.aml import compile_source
from cellctl.ui.common import MachineGroup, console, machine_ref, run

Action = Callable[[Ibm7545Robot], Awaitable[None]]


def _config(options: dict[str, Any]) -> RobotConfig:
    fields = set(RobotConfig.__dataclass_fields__)
    unknown = set(options) - fields
    if unknown:
        raise UsageError(f"unknown robot option(s) in cell.toml: {', '.join(sorted(unknown))}")
    return RobotConfig(**options)


def _with_robot(ctx: click.Context, action: Action) -> None:
    params = ctx.find_object(dict) or {}

    async def main() -> None:
        directory, ref = machine_ref(ctx, "robot")
        robot = await Ibm7545Robot.connect(
            ref.url,
            name=ref.name,
            settings=ref.settings,
            store=StateStore(directory),
            config=_config(ref.options),
            trace=params.get("trace"),
        )
        async with robot:
            await action(robot)

    run(main)


@click.group(cls=MachineGroup)
@click.option("--link", metavar="URL", help="Device path, socket://, rfc2217:// or loop://.")
@click.option("--line", metavar="SETTINGS", help="Line settings, e.g. 4800,7E2 (the default).")
@click.option(
    "--trace", type=click.Path(dir_okay=False), help="Write every byte both ways to this file."
)
@click.pass_context
def robot(ctx: click.Context, link: str | None, line: str | None, trace: str | None) -> None:
    """IBM 7545/7547 robot controller: [--link URL | NAME] COMMAND."""
    ctx.obj = {"link": link, "line": line, "trace": trace}


@robot.command()
@click.pass_context
def init(ctx: click.Context) -> None:
    """Return home, then auto mode (robot state 1)."""

    async def action(r: Ibm7545Robot) -> None:
        console.print("returning home")
        await r.return_home()
        await r.auto_mode()
        console.print("Set on Auto mode")
        console.print("Initializing was correct")

    _with_robot(ctx, action)


@robot.command()
@click.argument("partition", type=int)
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
@click.pass_context
def download(ctx: click.Context, partition: int, file: Path) -> None:
    """Download a compiled program file (.rec) into PARTITION 1-5."""
    from cellctl.protocol.robot import ProgramFile, encode_record

    if not 1 <= partition <= 5:
        raise click.BadParameter("partition must be 1 to 5 (partition error)")
    program = ProgramFile.load(file) if file.exists() else None
    if program is None:
        raise click.BadParameter(f"{file}: could not open file")
    total_bytes = sum(len(encode_record(r)) for r in program.records)

    async def action(r: Ibm7545Robot) -> None:
        columns = (
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("records  {task.fields[sent]}/{task.fields[total_bytes]} B"),
            TextColumn("{task.fields[rate]:>6.1f} chars/s"),
            TimeRemainingColumn(),
        )
        start = time.monotonic()
        with Progress(*columns, console=console, transient=False) as bar:
            task = bar.add_task(
                f"{program.name} -> partition {partition}",
                total=len(program.records),
                sent=0,
                total_bytes=total_bytes,
                rate=0.0,
            )

            def progress(done: int, total: int, sent: int) -> None:
                rate = sent / max(time.monotonic() - start, 1e-6)
                bar.update(task, completed=done, sent=sent, rate=rate)

            await r.download(partition, program, progress=progress)
        console.print("Download was correct")

    _with_robot(ctx, action)


@robot.command()
@click.argument("partition", type=int)
@click.pass_context
def go(ctx: click.Context, partition: int) -> None:
    """Run the program in PARTITION 1-5 (select application, start cycle)."""
    if not 1 <= partition <= 5:
        raise click.BadParameter("partition must be 1 to 5 (starting function error)")

    async def action(r: Ibm7545Robot) -> None:
        await r.go(partition)
        console.print("Started Cycle")

    _with_robot(ctx, action)


@robot.command()
@click.pass_context
def stop(ctx: click.Context) -> None:
    """Stop the cycle (robot state 1)."""

    async def action(r: Ibm7545Robot) -> None:
        console.print("Stopping Cycle")
        await r.stop()
        console.print("Cycle stopped")

    _with_robot(ctx, action)


@robot.command()
@click.pass_context
def halt(ctx: click.Context) -> None:
    """Stop the cycle and treat the robot as uninitialized (partitions flushed)."""

    async def action(r: Ibm7545Robot) -> None:
        await r.halt()
        console.print("Halted: robot uninitialized, every partition must be downloaded again")

    _with_robot(ctx, action)


@robot.command()
@click.pass_context
def status(ctx: click.Context) -> None:
    """Robot state, decoded status bytes, partitions Full/Empty."""

    async def action(r: Ibm7545Robot) -> None:
        st = await r.status()
        table = Table(title=f"{r.name}", show_header=False)
        table.add_row("Robot state", f"{st.state} ({st.state_text})")
        table.add_row(
            "Machine status",
            f"{st.machine} (bytes {st.machine.flags:02X} {st.machine.data_error:02X})",
        )
        for p, prog in st.partitions.items():
            table.add_row(f"Partition {p}", f"Full ({prog})" if prog else "Empty")
        console.print(table)

    _with_robot(ctx, action)


@robot.command()
@click.pass_context
def reject(ctx: click.Context) -> None:
    """The reject status: why the controller last refused a request."""

    async def action(r: Ibm7545Robot) -> None:
        code, message = await r.reject_status()
        console.print(f"Reject status {code}: {message}")

    _with_robot(ctx, action)


@robot.command()
@click.pass_context
def io(ctx: click.Context) -> None:
    """The 16 digital inputs and 16 outputs."""

    async def action(r: Ibm7545Robot) -> None:
        dido = await r.io()
        table = Table(title=f"{r.name} DI/DO")
        table.add_column("line", justify="right")
        for n in range(1, 17):
            table.add_column(str(n), justify="center")
        table.add_row("DI", *("1" if dido.input(n) else "." for n in range(1, 17)))
        table.add_row("DO", *("1" if dido.output(n) else "." for n in range(1, 17)))
        console.print(table)

    _with_robot(ctx, action)


@robot.command()
@click.pass_context
def reset(ctx: click.Context) -> None:
    """Error reset (ERRESET): clear machine-status and reject-status errors."""

    async def action(r: Ibm7545Robot) -> None:
        await r.reset_errors()
        console.print("Errors reset")

    _with_robot(ctx, action)


@robot.command()
@click.pass_context
def home(ctx: click.Context) -> None:
    """Return the arm home."""

    async def action(r: Ibm7545Robot) -> None:
        console.print("returning home")
        await r.return_home()
        console.print("Home")

    _with_robot(ctx, action)


@robot.command()
@click.argument("source", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "-o", "--output", type=click.Path(dir_okay=False, path_type=Path), help="Program file."
)
@click.option("--partition", type=click.IntRange(1, 5), default=1, show_default=True)
@click.option("--name", help="Application name (8 characters; default: the file's stem).")
def compile(source: Path, output: Path | None, partition: int, name: str | None) -> None:
    """Compile an AML/E source file into a program file of records (.rec)."""

    def main() -> None:
        try:
            text = source.read_text(encoding="utf-8")
        except OSError as e:
            raise UsageError(f"{source}: could not open file: {e.strerror}") from None
        app = (name or source.stem).upper().replace("-", "").replace("_", "")[:8]
        program = compile_source(text, app, partition, source=str(source))
        target = output or source.with_suffix(".rec")
        target.write_text(program.to_text(), encoding="ascii")
        console.print(f"{source} -> {target}: {len(program.body)} instructions, name {app}")

    async def amain() -> None:
        main()

    run(amain)
