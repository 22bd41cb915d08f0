"""``cellctl kinds``: the machine kinds installed, and where each comes from."""

from __future__ import annotations

import click
from rich.markup import escape
from rich.table import Table

from cellctl.kinds import registry
from cellctl.ui.common import console, json_option, print_json, print_table


@click.command("kinds")
@json_option
def kinds_command(as_json: bool) -> None:
    """List the machine kinds installed: family, maker and model, where each comes from.

    Kinds register under the entry-point group cellctl.machine_kinds (docs/kinds.md); one that
    cannot be loaded is listed as broken, with why, and the rest work.
    """
    if as_json:
        print_json(
            [
                {
                    "kind": k.name,
                    "family": k.family,
                    "maker": k.maker,
                    "model": k.model,
                    "distribution": k.origin.distribution if k.origin else None,
                    "module": k.origin.module if k.origin else None,
                }
                for k in registry.kinds()
            ]
            + [{"kind": name, "broken": why} for name, why in registry.broken().items()]
        )
        return
    table = Table(box=None, pad_edge=False)
    for column in ("kind", "family", "maker", "model", "from"):
        # "from" folds rather than cut: the module is what a user looks for. A long model
        # wraps at its words, so "from" keeps room for its distribution's name.
        wraps = column in ("model", "from")
        table.add_column(column, no_wrap=not wraps, overflow="fold")
    # On a terminal, the distribution, then the module on a line of its own: whole at 80
    # columns. Piped, one line per kind (print_table), as docs/kinds.md shows it.
    piped = not console.is_terminal
    for kind in registry.kinds():
        o = kind.origin
        if o is None:
            origin = "?"
        else:
            origin = f"{o.distribution} ({o.module})" if piped else f"{o.distribution}\n{o.module}"
        table.add_row(kind.name, kind.family, kind.maker, kind.model, origin)
    for name, why in registry.broken().items():
        table.add_row(name, "-", "-", "-", f"[red]broken: {escape(why)}[/red]")
    print_table(table)
