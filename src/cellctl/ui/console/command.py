"""``cellctl console``: open the cell (through its controller, or standalone) and run the
console on it; or attach to the server running on another directory (``--dir``)."""

from __future__ import annotations

import shlex
from pathlib import Path

import click

from cellctl.errors import with_article
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
    from cellctl.ui.console.session import is_cell, open_console_cell

    chosen = directory if directory is not None else cell_dir(ctx)
    server = None if is_cell(chosen) else server_of(ctx, chosen)

    async def main() -> None:
        client = await open_console_cell(chosen, server)
        app = ConsoleApp(chosen, client)
        try:
            await app.run_async()
        finally:
            await client.close()
        if app.startup_error is not None:
            fail(app.startup_error)

    run(main)


def server_of(ctx: click.Context, directory: Path) -> str | None:
    """What serves ``directory`` when it holds a server's configuration instead of a cell's,
    and how to start it: a ``NAME.toml`` of a command group that has ``serve`` (a shop's
    dnc.toml: ``cellctl dnc serve --dir shop``), with that group's summary; None if none."""
    root = ctx.find_root()
    top = root.command
    if not isinstance(top, click.Group):
        return None
    for config in sorted(directory.glob("*.toml")):
        group = top.get_command(root, config.stem)
        if isinstance(group, click.Group) and group.get_command(root, "serve") is not None:
            start = f"cellctl {config.stem} serve --dir {shlex.quote(str(directory))}"
            summary = group.get_short_help_str(limit=200)
            return f"{with_article(config.name)} ({summary}): start it with `{start}`"
    return None
