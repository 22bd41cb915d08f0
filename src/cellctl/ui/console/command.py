"""``cellctl console``: open the cell (through its controller, or standalone) and run the
console on it."""

from __future__ import annotations

import click

from cellctl.ui.common import cell_dir, fail, run


@click.command("console")
@click.pass_context
def console_command(ctx: click.Context) -> None:
    """The operator console: the source's menus, the cell's board and traffic, live.

    Attached to `cellctl run` when a controller runs on the cell (everything through its
    API); standalone otherwise (the console opens the machines' links itself).
    """
    from cellctl.ui.console.app import ConsoleApp
    from cellctl.ui.console.session import open_console_cell

    directory = cell_dir(ctx)

    async def main() -> None:
        client = await open_console_cell(directory)
        app = ConsoleApp(directory, client)
        try:
            await app.run_async()
        finally:
            await client.close()
        if app.startup_error is not None:
            fail(app.startup_error)

    run(main)
