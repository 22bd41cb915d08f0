"""Every manual function of a machine, once: each kind's menu (the source's robot and CNC
menus plus the tool-kit's extras), read from the registry. The CLI, the control API and the
console all run them from here::

    fn = function("robot", "download")
    params = fn.check({"partition": 3, "program": "load1.rec", "text": text})  # no byte yet
    result = await fn.run(robot, params, progress)     # {"message": "Download was correct", ...}

A family's functions are those of its kinds; where two kinds of a family both have a function
of one name, :func:`function` with ``kind`` picks that kind's.
"""

from __future__ import annotations

from functools import cache

from cellctl.errors import UsageError
from cellctl.kinds import registry
from cellctl.kinds.kind import FAMILIES
from cellctl.kinds.menu import (
    MAX_PROGRAM_CHARS,
    InvalidParams,
    MachineFunction,
    NoParams,
    Params,
    Prepared,
    ProgramParams,
    Progress,
    describe,
)

__all__ = [
    "FAMILIES",
    "MAX_PROGRAM_CHARS",
    "InvalidParams",
    "MachineFunction",
    "NoParams",
    "Params",
    "Prepared",
    "ProgramParams",
    "Progress",
    "describe",
    "family_of_kind",
    "function",
    "functions",
    "kind_menu",
    "menu",
    "state_text",
]


def kind_menu(kind: str) -> list[MachineFunction]:
    """The manual functions kind ``kind`` declares (none if it declares no menu)."""
    declared = registry.kind(kind).menu
    return list(declared()) if declared is not None else []


def _family_functions() -> tuple[MachineFunction, ...]:
    seen: dict[tuple[str, str], MachineFunction] = {}
    for family in FAMILIES:  # the robot's functions first, then the mills', as the source
        for k in registry.kinds(family):
            for fn in kind_menu(k.name):
                seen.setdefault((fn.family, fn.name), fn)
    return tuple(seen.values())


@cache
def functions() -> tuple[MachineFunction, ...]:
    """Every family's functions (the first kind declaring a name gives it): the control API
    serves each as FAMILY.NAME, and a call runs the function of the machine's own kind."""
    return _family_functions()


def family_of_kind(kind: str) -> str | None:
    """The family of machine kind ``kind`` (as in cell.toml); None if it is not installed."""
    try:
        return registry.family_of(kind)
    except UsageError:
        return None


def function(family: str, name: str, kind: str | None = None) -> MachineFunction:
    """The function ``name`` of ``family`` (of ``kind``, if given); UsageError naming the known
    ones otherwise."""
    mine = kind_menu(kind) if kind is not None else [f for f in functions() if f.family == family]
    for fn in mine:
        if fn.family == family and fn.name == name:
            return fn
    known = ", ".join(f.name for f in mine if f.family == family)
    of = f" on a {kind}" if kind is not None else ""
    raise UsageError(f"no {family} function {name!r}{of} (known: {known})")


def menu(family: str, kind: str | None = None) -> list[MachineFunction]:
    """The functions (of ``kind``, else the family's), the source's menu first (by number),
    then the extras."""
    mine = kind_menu(kind) if kind is not None else [f for f in functions() if f.family == family]
    return sorted(mine, key=lambda f: (f.menu is None, f.menu or 0))


def state_text(kind: str, state: int) -> str:
    """A machine's state number in words, as kind ``kind`` names it."""
    return registry.kind(kind).states.words(state)
