"""Which machine a command means: ``--link URL`` or a NAME from the cell's ``cell.toml``.

``cell.toml`` (in the cell directory, ``--cell DIR`` or ``$CELLCTL_CELL``, default ``cell``)::

    [machines.robot1]
    kind = "..."                          # a kind `cellctl kinds` lists
    link = "rfc2217://127.0.0.1:7001"
    line = "4800,7E2"                     # optional; the kind's default otherwise
    options = { reply_timeout = 2.0 }     # optional driver settings

A command given neither ``--link`` nor a NAME uses the cell's only machine of that kind.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cellctl.errors import UsageError, with_article
from cellctl.files import read_file, reason
from cellctl.kinds import registry
from cellctl.link import LineSettings


@dataclass(frozen=True)
class MachineRef:
    """A resolved machine: its name (keys its saved state), link URL, line and options."""

    name: str
    kind: str
    url: str
    settings: LineSettings
    options: dict[str, Any] = field(default_factory=dict)


def load_cell_file(cell_dir: Path) -> dict[str, Any]:
    """The parsed ``cell.toml`` of ``cell_dir``, or ``{}`` if there is none."""
    path = cell_dir / "cell.toml"
    try:
        data = read_file(path)  # a regular file only: a FIFO there would block for ever
    except FileNotFoundError:
        return {}
    except OSError as e:
        raise UsageError(f"{path}: cannot read: {reason(e)}") from None
    try:
        return tomllib.loads(data.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise UsageError(f"{path}: not valid TOML: {e}") from None


def resolve_machine(
    cell_dir: Path,
    family: str,
    *,
    name: str | None,
    link: str | None,
    line: str | None = None,
    kind: str | None = None,
    function: str | None = None,
) -> MachineRef:
    """Resolve ``--link``/NAME for a ``family`` (``robot`` or ``mill``); refuses unknown names.

    ``kind`` (``--kind``) is the machine's kind: at ``--link``, what the link is driven as;
    with a NAME, it must be the kind cell.toml gives; with neither, it picks the cell's only
    machine of that kind. At ``--link`` without it, the family's first kind is taken, unless
    only other kinds of the family have ``function`` (``cellctl robot --link URL unlock``).
    """
    kinds = registry.names(family)
    if not kinds:
        raise UsageError(f"no {family} kind is installed (`cellctl kinds` lists them)")
    if kind is not None and kind not in kinds:
        raise UsageError(f"{kind!r} is not a {family} kind (installed: {', '.join(kinds)})")
    if link:
        chosen = kind or _kind_for(family, kinds, function)
        settings = LineSettings.parse(line) if line else registry.kind(chosen).line_settings
        return MachineRef(name or link, chosen, link, settings)
    if not (cell_dir / "cell.toml").exists():
        raise UsageError(
            f"no {cell_dir / 'cell.toml'}: give --link URL, or --cell DIR of a cell "
            "(`cellctl emulate cell` writes one)"
        )
    machines: dict[str, Any] = load_cell_file(cell_dir).get("machines", {})
    wanted = kinds if kind is None else (kind,)
    mine = {n: m for n, m in machines.items() if isinstance(m, dict) and m.get("kind") in wanted}
    what = family if kind is None else f"{family} of kind {kind}"
    if name is None:
        if len(mine) == 1:
            name = next(iter(mine))
        else:
            known = ", ".join(sorted(mine)) or f"none in {cell_dir / 'cell.toml'}"
            raise UsageError(f"which {what}? give --link URL or a NAME (known: {known})")
    if name not in machines:
        known = ", ".join(sorted(mine)) or f"none in {cell_dir / 'cell.toml'}"
        raise UsageError(f"unknown {what} {name!r} (known: {known})")
    entry = machines[name]
    found = entry.get("kind")
    if found not in kinds or not entry.get("link"):
        # A kind not installed (a typo), a missing link: said as `cellctl cell check` says it.
        from cellctl.cell.config import refuse_machine

        refuse_machine(cell_dir, name)
    if found not in kinds:
        raise UsageError(f"machine {name!r} is {with_article(repr(found))}, not a {family}")
    if kind is not None and found != kind:
        raise UsageError(
            f"machine {name!r} is {with_article(repr(found))}, not {with_article(repr(kind))} "
            "(cell.toml)"
        )
    if not entry.get("link"):
        raise UsageError(f"machine {name!r} has no link URL in cell.toml")
    text = line or entry.get("line")
    settings = LineSettings.parse(text) if text else registry.kind(found).line_settings
    return MachineRef(name, found, str(entry["link"]), settings, dict(entry.get("options", {})))


def _kind_for(family: str, kinds: tuple[str, ...], function: str | None) -> str:
    """The kind a machine at ``--link`` is driven as when no ``--kind`` is given: the
    family's first, unless only others have ``function``."""
    from cellctl.service.functions import kind_menu

    having = [
        k for k in kinds if any(f.family == family and f.name == function for f in kind_menu(k))
    ]
    return having[0] if having and kinds[0] not in having else kinds[0]
