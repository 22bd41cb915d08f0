"""A family group's check that the machine a command names has its function: ``cellctl mill
saw go`` refused before anything is read or sent, naming what the command line has for the
saw's kind (docs/kinds.md). :func:`~cellctl.ui.common.kind_commands` gives every command of
the family groups the check, once their kinds' commands are added::

    check_kinds(mill_group)
"""

from __future__ import annotations

import click

from cellctl.errors import UsageError, with_article

#: The name of the check :func:`check_kinds` adds to a family group's commands.
_KIND_CHECK = "kind_has_command"


def check_kinds(group: click.Group) -> None:
    """Give each command of a family's group (``cellctl mill``; a subgroup's commands, not the
    subgroup: ``robot io set``) the check that the machine it names has its function
    (:func:`_refuse_other_kinds`): once, whoever contributed it. A subgroup's own check
    would come before its --help or subcommand is known."""
    for command in group.commands.values():
        subs = command.commands.values() if isinstance(command, click.Group) else (command,)
        for checked in subs:
            if not any(p.name == _KIND_CHECK for p in checked.params):
                checked.params.append(
                    click.Option(
                        [f"--{_KIND_CHECK}"],
                        hidden=True,
                        expose_value=False,
                        callback=_refuse_other_kinds,
                    )
                )


def _refuse_other_kinds(ctx: click.Context, param: click.Parameter, value: object) -> None:
    """Refuse ``cellctl mill saw go`` when the saw's kind has no ``go``, before anything is read
    or sent, naming the commands the command line has for it (the family's commands it has a
    function for: docs/kinds.md) and where its other functions are (the console, the API)."""
    from cellctl.service.functions import functions, kind_menu
    from cellctl.ui.common import MachineGroup, machine_ref
    from cellctl.ui.machine_group import kind_offer

    words = [ctx.command.name or ""]
    above = ctx.parent
    while above is not None and not isinstance(above.command, MachineGroup):
        words.insert(0, above.command.name or "")
        above = above.parent
    group, family = (above.command, above.command.name) if above is not None else (None, None)
    if group is None or family is None or not isinstance(group, click.Group):
        return
    function = "_".join(words)
    if all(f.name != function for f in functions() if f.family == family):
        return  # a command that calls no machine (`mill check`): nothing to refuse
    _, ref = machine_ref(ctx, family, function)
    if any(f.name == function for f in kind_menu(ref.kind) if f.family == family):
        return
    said = kind_offer(group, family, ref.kind)
    command = " ".join(words)
    raise UsageError(
        f"no {family} command {command!r} for {ref.name}, {with_article(ref.kind)} ({said})"
    )
