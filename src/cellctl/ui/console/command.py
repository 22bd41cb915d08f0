"""``cellctl console``: open the cell (through its controller, or standalone) and run the
console on it; or attach to the server running on another directory (``--dir``)."""

from __future__ import annotations

from pathlib import Path

import click

from cellctl.ui.common import cell_dir, fail, run


@click.command("console")
@click.option(
    "--dir",
    "directory",
    type=click.Path(file_okay=False, path_type=Path),
    help="Attach to the server running on this directory instead of the cell: a shop "
    "served by `cellctl dnc serve --dir DIR` (its machines, their menus from the server).",
)
@click.pass_context
def console_command(ctx: click.Context, directory: Path | None) -> None:
    """The operator console: the source's menus, the cell's board and traffic, live.

    Attached to `cellctl run` when a controller runs on the cell (everything through its
    API); standalone otherwise (the console opens the machines' links itself). With --dir,
    attached to the server running there (a DNC server's shop).
    """
    from cellctl.ui.console.app import ConsoleApp
    from cellctl.ui.console.session import open_console_cell

    chosen = directory if directory is not None else cell_dir(ctx)

    async def main() -> None:
        client = await open_console_cell(chosen)
        app = ConsoleApp(chosen, client)
        try:
            await app.run_async()
        finally:
            await client.close()
        if app.startup_error is not None:
            fail(app.startup_error)

    run(main)
