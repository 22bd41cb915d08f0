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

A name is one kind. A built-in kind (declared by cellctl itself) always wins: a plug-in
declaring its name is listed broken ("mill1 is a built-in kind: cellctl-x cannot replace
it") and never imported. Two plug-ins declaring one name are both refused (which one a user
meant, cellctl cannot know): the name is listed broken naming both distributions.

Tests make kinds of their own visible in their process with :func:`registered` (a testing
hook: nothing installed, nothing left behind)::

    with registry.registered(dataclasses.replace(registry.kind("saw1"), name="saw1-x")):
        ...
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Callable, Iterable, Iterator
from functools import cache
from importlib.metadata import EntryPoint, entry_points
from typing import TYPE_CHECKING

from cellctl.errors import CellctlError, UsageError
from cellctl.kinds.kind import FAMILIES, EmulatorSpec, MachineKind, Origin

if TYPE_CHECKING:
    from cellctl.emulators.serve import EmulatedDevice

GROUP = "cellctl.machine_kinds"
#: The distribution of the kinds cellctl ships: a plug-in cannot replace one of them.
BUILT_IN = "cellctl"

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
    if obj.options.model_config.get("extra") != "forbid":
        # Else a mistyped option in a cell.toml passes `cell check` and is dropped unsaid.
        raise ValueError(
            f"its options model {obj.options.__name__} must refuse unknown keys "
            '(model_config = ConfigDict(extra="forbid"))'
        )
    dist = ep.dist.name if ep.dist is not None else "?"
    if dist == BUILT_IN:
        return dataclasses.replace(obj, origin=Origin(dist, ep.module))
    emulator = _guarded_emulator(obj.emulator, f"kind {obj.name} (from {dist})")
    return dataclasses.replace(obj, origin=Origin(dist, ep.module), emulator=emulator)


def _guarded_emulator(
    make: Callable[[EmulatorSpec], EmulatedDevice], who: str
) -> Callable[[EmulatorSpec], EmulatedDevice]:
    """A plug-in's emulator hook whose failure is a typed error naming the kind (``emulate
    cell`` then says which, instead of a traceback)."""

    def guarded(spec: EmulatorSpec) -> EmulatedDevice:
        try:
            return make(spec)
        except CellctlError:
            raise
        except Exception as e:  # a plug-in's failure of any kind: said, not a traceback
            raise UsageError(f"{who}: its emulator failed to start: {type(e).__name__}: {e}") from e

    return guarded


@cache
def _try(ep: EntryPoint) -> MachineKind | str:
    """The kind entry point ``ep`` declares, or why it gave none (loaded once per process)."""
    try:
        return _load(ep)
    except Exception as e:  # a plug-in's failure of any kind: skip it, say which
        why = f"{type(e).__name__}: {e}"
        log.warning("machine kind %s skipped: %s", ep.name, why)
        return why


def _dist(ep: EntryPoint) -> str:
    return ep.dist.name if ep.dist is not None else "?"


def _chosen(name: str, eps: list[EntryPoint]) -> EntryPoint | str:
    """Which of the entry points declaring kind ``name`` is used, or why none is: a built-in
    one wins over any plug-in; two plug-ins are both refused."""
    built_in = [ep for ep in eps if _dist(ep) == BUILT_IN]
    if built_in:
        return built_in[0]
    dists = sorted({_dist(ep) for ep in eps})
    if len(eps) == 1:
        return eps[0]
    if len(dists) == 1:  # one distribution declaring it twice: its own mistake
        return f"declared twice by {dists[0]} ({', '.join(sorted(ep.value for ep in eps))})"
    return f"declared by {' and '.join(dists)}: neither is used (uninstall one, or rename its kind)"


def _refused(name: str, eps: list[EntryPoint], used: EntryPoint | None) -> str | None:
    """Why plug-in entry points beside the one used (a built-in kind) are skipped; warned
    once, as any broken plug-in is."""
    others = sorted({_dist(ep) for ep in eps if ep is not used})
    if used is None or not others:
        return None
    why = f"{name} is a built-in kind: {', '.join(others)} cannot replace it"
    log.warning("machine kind %s skipped: %s", name, why)
    return why


def _grouped(eps: Iterable[EntryPoint]) -> dict[str, list[EntryPoint]]:
    by_name: dict[str, list[EntryPoint]] = {}
    for ep in sorted(eps, key=lambda e: (e.name, _dist(e), e.value)):
        by_name.setdefault(ep.name, []).append(ep)
    return by_name


@cache
def _declared() -> dict[str, list[EntryPoint]]:
    """The group's entry points by name (read once per process; nothing imported)."""
    return _grouped(entry_points(group=GROUP))


@cache
def _resolved(name: str) -> tuple[MachineKind | None, str]:
    """Kind ``name`` from the entry points declaring it, and why a declaration is skipped
    ("" when none is): the one rule :func:`found` and :func:`kind` share."""
    eps = _declared().get(name, [])
    if not eps:
        return None, ""  # no such kind: unknown, not broken
    chosen = _chosen(name, eps)
    if isinstance(chosen, str):
        log.warning("machine kind %s skipped: %s", name, chosen)
        return None, chosen
    refused = _refused(name, eps, chosen) or ""
    k = _try(chosen)
    if isinstance(k, MachineKind):
        return k, refused
    return None, k


@cache
def found() -> Found:
    """Every kind the entry points declare (read once per process)."""
    kinds: dict[str, MachineKind] = {}
    broken: dict[str, str] = {}
    for name in _declared():
        k, why = _resolved(name)
        if k is not None:
            kinds[name] = k
        if why:
            broken[name] = why
    return Found(kinds, broken)


def _one(name: str) -> MachineKind | str:
    """Kind ``name`` alone, as :func:`found` would give it (a command about one cell's
    machines imports no other kind's package), or why it gave none."""
    if name in _testing:
        return _testing[name]
    k, why = _resolved(name)
    return k if k is not None else why


#: Kinds a test made visible in this process (:func:`registered`).
_testing: dict[str, MachineKind] = {}


@contextlib.contextmanager
def registered(*added: MachineKind, distribution: str = "tests") -> Iterator[None]:
    """A testing hook: ``added`` are kinds of this process (origin ``distribution``) for the
    ``with`` block, as if installed; a built-in or installed kind's name is refused."""
    for k in added:
        if k.name in found().kinds or k.name in _testing:
            raise ValueError(f"kind {k.name!r} is installed already")
    for k in added:
        emulator = _guarded_emulator(k.emulator, f"kind {k.name} (from {distribution})")
        _testing[k.name] = dataclasses.replace(
            k, origin=Origin(distribution, "tests"), emulator=emulator
        )
    try:
        yield
    finally:
        for k in added:
            _testing.pop(k.name, None)


def kinds(family: str | None = None) -> list[MachineKind]:
    """The installed kinds (of ``family``), by name."""
    every = [*found().kinds.values(), *_testing.values()]
    return [k for k in every if family is None or k.family == family]


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
