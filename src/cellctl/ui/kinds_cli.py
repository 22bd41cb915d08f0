"""``cellctl kinds``: the machine kinds installed, and where each comes from."""

from __future__ import annotations

import dataclasses

import click
from rich.markup import escape
from rich.table import Table

from cellctl.kinds import registry
from cellctl.kinds.kind import BrokenKind, LazyTable, MachineKind
from cellctl.ui.common import console, json_option, print_json, print_table


def _broken_tables(kind: MachineKind) -> str:
    """Why a plug-in kind's tables cannot be read ("" when they can): read here, as using
    the kind would, so a kind listed as fine is one that works. A built-in kind's are
    cellctl's own (reading them would import every emulator)."""
    if kind.origin is None or kind.origin.distribution == registry.BUILT_IN:
        return ""
    for field in dataclasses.fields(kind):
        table = getattr(kind, field.name)
        if isinstance(table, LazyTable):
            try:
                table.read()
            except BrokenKind as e:
                return str(e)
    return ""


@click.command("kinds")
@json_option
def kinds_command(as_json: bool) -> None:
    """List the machine kinds installed: family, maker and model, where each comes from.

    Kinds register under the entry-point group cellctl.machine_kinds (docs/kinds.md); one that
    cannot be loaded is listed as broken, with why, and the rest work.
    """
    found = registry.kinds()
    unreadable = {k.name: why for k in found if (why := _broken_tables(k))}
    found = [k for k in found if k.name not in unreadable]
    # A plug-in refused for a built-in kind's name is listed beside the built-in one.
    broken = [*unreadable.items(), *registry.broken().items()]
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
                for k in found
            ]
            + [{"kind": name, "broken": why} for name, why in broken]
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
    for kind in found:
        o = kind.origin
        if o is None:
            origin = "?"
        else:
            origin = f"{o.distribution} ({o.module})" if piped else f"{o.distribution}\n{o.module}"
        table.add_row(kind.name, kind.family, kind.maker, kind.model, origin)
    for name, why in broken:
        table.add_row(name, "-", "-", "-", f"[red]broken: {escape(why)}[/red]")
    print_table(table)
