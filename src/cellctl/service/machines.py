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

from cellctl.errors import UsageError
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
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        return {}
    except tomllib.TOMLDecodeError as e:
        raise UsageError(f"{path}: not valid TOML: {e}") from None


def resolve_machine(
    cell_dir: Path,
    family: str,
    *,
    name: str | None,
    link: str | None,
    line: str | None = None,
) -> MachineRef:
    """Resolve ``--link``/NAME for a ``family`` (``robot`` or ``mill``); refuses unknown names."""
    kinds = registry.names(family)
    if not kinds:
        raise UsageError(f"no {family} kind is installed (`cellctl kinds` lists them)")
    if link:
        settings = LineSettings.parse(line) if line else registry.kind(kinds[0]).line_settings
        return MachineRef(name or link, kinds[0], link, settings)
    if not (cell_dir / "cell.toml").exists():
        raise UsageError(
            f"no {cell_dir / 'cell.toml'}: give --link URL, or --cell DIR of a cell "
            "(`cellctl emulate cell` writes one)"
        )
    machines: dict[str, Any] = load_cell_file(cell_dir).get("machines", {})
    mine = {n: m for n, m in machines.items() if isinstance(m, dict) and m.get("kind") in kinds}
    if name is None:
        if len(mine) == 1:
            name = next(iter(mine))
        else:
            known = ", ".join(sorted(mine)) or f"none in {cell_dir / 'cell.toml'}"
            raise UsageError(f"which {family}? give --link URL or a NAME (known: {known})")
    if name not in machines:
        known = ", ".join(sorted(mine)) or f"none in {cell_dir / 'cell.toml'}"
        raise UsageError(f"unknown {family} {name!r} (known: {known})")
    entry = machines[name]
    kind = entry.get("kind")
    if kind not in kinds:
        raise UsageError(f"machine {name!r} is a {kind!r}, not a {family}")
    if not entry.get("link"):
        raise UsageError(f"machine {name!r} has no link URL in cell.toml")
    text = line or entry.get("line")
    settings = LineSettings.parse(text) if text else registry.kind(kind).line_settings
    return MachineRef(name, kind, str(entry["link"]), settings, dict(entry.get("options", {})))
