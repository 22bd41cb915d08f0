"""The machine kinds installed here, found through the entry-point group
``cellctl.machine_kinds``: the 1988 kinds register there like any other.

::

    from cellctl.kinds import registry
    kind = registry.kind("saw1")            # UsageError naming the known kinds otherwise
    registry.kinds("mill")                  # every kind of the mill family
    registry.broken()                       # {entry-point name: why it was skipped}

A plug-in declares ``[project.entry-points."cellctl.machine_kinds"]`` ``NAME =
"package.module:KIND"`` where ``KIND`` is a :class:`~cellctl.kinds.kind.MachineKind` (or a
function returning one) whose ``name`` is ``NAME``. One that fails to import or declares
something else is reported by name and skipped, never a crash at start.
"""

from __future__ import annotations

import dataclasses
import logging
from functools import cache
from importlib.metadata import EntryPoint, entry_points

from cellctl.errors import UsageError
from cellctl.kinds.kind import FAMILIES, MachineKind, Origin

GROUP = "cellctl.machine_kinds"

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Found:
    """What the entry points gave: the kinds by name, and the broken ones with why."""

    kinds: dict[str, MachineKind]
    broken: dict[str, str]


def _load(ep: EntryPoint) -> MachineKind:
    obj = ep.load()
    if not isinstance(obj, MachineKind) and callable(obj):
        obj = obj()
    if not isinstance(obj, MachineKind):
        raise TypeError(f"{ep.value} is a {type(obj).__name__}, not a MachineKind")
    if obj.name != ep.name:
        raise ValueError(f"{ep.value} declares kind {obj.name!r} under the name {ep.name!r}")
    if obj.family not in FAMILIES:
        raise ValueError(f"family {obj.family!r} is not one of {', '.join(FAMILIES)}")
    obj.line_settings  # noqa: B018 - a bad default line is the plug-in's fault: found here
    dist = ep.dist.name if ep.dist is not None else "?"
    return dataclasses.replace(obj, origin=Origin(dist, ep.module))


@cache
def _try(ep: EntryPoint) -> MachineKind | str:
    """The kind entry point ``ep`` declares, or why it gave none (loaded once per process)."""
    try:
        return _load(ep)
    except Exception as e:  # a plug-in's failure of any kind: skip it, say which
        why = f"{type(e).__name__}: {e}"
        log.warning("machine kind %s skipped: %s", ep.name, why)
        return why


@cache
def found() -> Found:
    """Every kind the entry points declare (read once per process)."""
    kinds: dict[str, MachineKind] = {}
    broken: dict[str, str] = {}
    for ep in sorted(entry_points(group=GROUP), key=lambda e: e.name):
        if ep.name in kinds:
            broken[ep.name] = f"declared twice ({ep.value}); the first one is used"
            continue
        k = _try(ep)
        if isinstance(k, MachineKind):
            kinds[ep.name] = k
        else:
            broken[ep.name] = k
    return Found(kinds, broken)


@cache
def _one(name: str) -> MachineKind | str:
    """Kind ``name`` alone, as :func:`found` would give it (a command about one cell's
    machines imports no other kind's package), or why it gave none."""
    eps = [ep for ep in entry_points(group=GROUP) if ep.name == name]
    why = ""
    for ep in eps:
        k = _try(ep)
        if isinstance(k, MachineKind):
            return k
        why = k
    return why


def kinds(family: str | None = None) -> list[MachineKind]:
    """The installed kinds (of ``family``), by name."""
    return [k for k in found().kinds.values() if family is None or k.family == family]


def names(family: str | None = None) -> tuple[str, ...]:
    """The installed kinds' names (of ``family``)."""
    return tuple(k.name for k in kinds(family))


def kind(name: str) -> MachineKind:
    """The kind called ``name``; UsageError naming the known ones (and why it is broken)."""
    k = _one(name)
    if isinstance(k, MachineKind):
        return k
    if k:
        raise UsageError(f"machine kind {name!r} is installed but broken: {k}")
    raise UsageError(f"unknown machine kind {name!r} (known: {', '.join(names()) or 'none'})")


def family_of(name: str) -> str:
    """The family of kind ``name`` (``robot``, ``mill``)."""
    return kind(name).family


def broken() -> dict[str, str]:
    """Entry points that gave no kind: name -> why."""
    return dict(found().broken)
