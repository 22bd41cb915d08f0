"""A family's command group (``cellctl robot``, ``cellctl mill``): an optional machine NAME
before its command, and a command the machine's kind has not refused in words naming what
the command line has for it::

    @click.group(cls=MachineGroup)
    def mill(...): ...

    cellctl mill --kind KIND --link URL home
    # error: no mill command 'home' for URL, a KIND (its commands: status; its functions
    #        home, cut: in the console or the control API)
"""

from __future__ import annotations

import click

from cellctl.errors import UsageError, with_article


class MachineGroup(click.Group):
    """A group that takes an optional machine NAME before its command: ``robot r1 status``.

    A word that is no command of the group, or a NAME with no command after it, is refused
    naming the machine's kind and the commands it has (not Click's "No such command")."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        rest = list(args)
        # Options come first; the first bare word that is not a command is the machine NAME.
        name, i = None, 0
        while i < len(rest):
            word = rest[i]
            if word.startswith("-"):
                opt = self._option_for(ctx, word)
                i += 1 if opt is None or opt.is_flag or "=" in word else 2
                continue
            if word not in self.commands:
                name = word
            break
        # The last word at --link (where a NAME only labels the machine) is its command.
        taken = name is not None and not (i == len(rest) - 1 and _given(rest[:i], "--link"))
        if taken:
            ctx.meta["machine_name"] = name
            del rest[i]
        # A NAME and no command after it: refused once the options are read (Click would
        # show the help for no word at all, or say "Missing command").
        alone = taken and i == len(rest) and not ctx.resilient_parsing
        parsed = super().parse_args(ctx, rest) if rest or not alone else []
        if alone:
            raise UsageError(kind_refusal(ctx, self, "given"))
        return parsed

    def resolve_command(
        self, ctx: click.Context, args: list[str]
    ) -> tuple[str | None, click.Command | None, list[str]]:
        word = args[0] if args else ""
        unknown = word[:1] not in ("", "-") and self.get_command(ctx, word) is None
        if unknown and not ctx.resilient_parsing:
            raise UsageError(kind_refusal(ctx, self, repr(word)))
        return super().resolve_command(ctx, args)

    def _option_for(self, ctx: click.Context, word: str) -> click.Option | None:
        name = word.split("=", 1)[0]
        for param in self.get_params(ctx):
            if isinstance(param, click.Option) and name in param.opts + param.secondary_opts:
                return param
        return None


def _given(args: list[str], option: str) -> bool:
    return any(a == option or a.startswith(option + "=") for a in args)


def kind_refusal(ctx: click.Context, group: click.Group, command: str) -> str:
    """``no mill command COMMAND for NAME, a KIND (its commands: ...)``: the machine the
    group's options and NAME mean (resolved as its commands resolve it) and what the command
    line has for its kind. ``command``: the word, quoted, or ``given`` when there was none."""
    from cellctl.service.machines import resolve_machine
    from cellctl.ui.common import cell_dir

    family = group.name or ""
    ref = resolve_machine(
        cell_dir(ctx),
        family,
        name=ctx.meta.get("machine_name"),
        link=ctx.params.get("link"),
        line=ctx.params.get("line"),
        kind=ctx.params.get("kind"),
    )
    return (
        f"no {family} command {command} for {ref.name}, {with_article(ref.kind)} "
        f"({kind_offer(group, family, ref.kind)})"
    )


def command_paths(group: click.Group) -> dict[str, str]:
    """Each command of a family's group by the function it runs: its name, or for a
    subgroup's, both words joined by ``_`` (``robot io set`` runs ``io_set``)."""
    paths = {word: word for word in group.commands}
    for word, command in group.commands.items():
        if isinstance(command, click.Group):
            paths.update({f"{word}_{sub}": f"{word} {sub}" for sub in command.commands})
    return paths


def kind_offer(group: click.Group, family: str, kind: str) -> str:
    """What the command line has for a machine of ``kind`` in ``family``'s ``group``: the
    commands it has a function for, and where its other functions are (docs/kinds.md)."""
    from cellctl.service.functions import kind_menu

    has = [f.name for f in kind_menu(kind) if f.family == family]
    paths = command_paths(group)
    offered = [said for name, said in sorted(paths.items()) if name in has]
    others = [name for name in has if name not in paths]
    said = f"its commands: {', '.join(offered) or 'none'}"
    if others:
        said += f"; its functions {', '.join(others)}: in the console or the control API"
    return said
