"""The machine kinds installed here, found through the entry-point group
``cellctl.machine_kinds``: the 1988 kinds register there like any other.

::

    from cellctl.kinds import registry
    kind = registry.kind("saw1")            # UsageError naming the known kinds otherwise,
                                            # BrokenKind for one installed but broken
    registry.kinds("mill")                  # every kind of the mill family
    registry.broken()                       # {entry-point name: why it was skipped}

A plug-in declares ``[project.entry-points."cellctl.machine_kinds"]`` ``NAME =
"package.module:KIND"`` where ``KIND`` is a :class:`~cellctl.kinds.kind.MachineKind` (or a
function returning one) whose ``name`` is ``NAME``. One that fails to import or declares
something else is reported by name and skipped, never a crash at start; named (a cell.toml,
``--kind``), it is :class:`~cellctl.kinds.kind.BrokenKind`: ``kind 'saw2' (package
cellctl-saw2) is installed but broken: WHY (WHAT TO FIX)``.

A plug-in kind is held to the contract docs/kinds.md gives as its hooks are used: the
emulator its hook makes must have its family's members (:data:`EMULATOR_MEMBERS`), and its
``start()`` and ``set_fault()`` failing, or its ``emulated_options`` giving options its own
model refuses, are said in words naming the kind; a ``LazyTable`` of its that cannot be read
breaks that kind alone (:class:`~cellctl.kinds.kind.LazyTable`).

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
import functools
import importlib
import inspect
import logging
from collections.abc import Callable, Iterable, Iterator, Mapping
from functools import cache
from importlib.metadata import EntryPoint, entry_points
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from cellctl.errors import CellctlError, UsageError
from cellctl.kinds.kind import FAMILIES, BrokenKind, EmulatorSpec, LazyTable, MachineKind, Origin

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


class _Refused(Exception):
    """Why an entry point gives no kind, in words whole (no exception type put before)."""


def _declared_object(ep: EntryPoint) -> object:
    """What entry point ``ep`` names, its failure said with what its author should fix."""
    try:
        module = importlib.import_module(ep.module)
    except ModuleNotFoundError as e:
        if e.name is not None and (ep.module == e.name or ep.module.startswith(e.name + ".")):
            raise _Refused(
                f"{type(e).__name__}: {e} (its entry point {ep.name} = {ep.value} names a "
                "module that is not there: fix it in the package's pyproject.toml)"
            ) from None
        raise _Refused(
            f"{type(e).__name__}: {e} (raised importing {ep.module}: install what it "
            "imports, or fix the import)"
        ) from None
    except Exception as e:  # its import raised: the package's own mistake
        raise _Refused(
            f"{type(e).__name__}: {e} (raised importing {ep.module}: fix the package's import)"
        ) from None
    obj: object = module
    for name in ep.attr.split(".") if ep.attr else ():
        try:
            obj = getattr(obj, name)
        except AttributeError as e:
            raise _Refused(
                f"{type(e).__name__}: {e} (its entry point {ep.name} = {ep.value} names "
                "nothing there: fix it in the package's pyproject.toml)"
            ) from None
    return obj


def _load(ep: EntryPoint) -> MachineKind:
    obj = _declared_object(ep)
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
    dist = _dist(ep)
    owner = f"kind {obj.name!r} (package {dist})"
    obj = dataclasses.replace(obj, origin=Origin(dist, ep.module), **_owned_tables(obj, owner))
    if dist == BUILT_IN:
        return obj
    return _held_to_contract(obj, f"kind {obj.name} (from {dist})", owner)


def _owned_tables(kind: MachineKind, owner: str) -> dict[str, Any]:
    """The kind's LazyTables, each saying ``owner`` and its field when it cannot be read."""
    return {
        f.name: value.owned(owner, f.name)
        for f in dataclasses.fields(kind)
        if isinstance(value := getattr(kind, f.name), LazyTable)
    }


def _held_to_contract(kind: MachineKind, who: str, owner: str) -> MachineKind:
    """A plug-in kind whose emulator and emulated options are checked as they are made: a
    mistake is a typed error naming the kind (``who``: ``kind saw1 (from cellctl-saw)``;
    ``owner``: ``kind 'saw1' (package cellctl-saw)``), never a traceback."""
    emulated = kind.emulated_options
    return dataclasses.replace(
        kind,
        emulator=_guarded_emulator(kind, who),
        emulated_options=None if emulated is None else _checked_emulated(kind, emulated, owner),
    )


#: What the emulated cell uses of an emulator of each family, besides ``session``
#: (docs/kinds.md, step 5); ``set_fault()`` and ``clear_fault()`` where the kind has faults.
EMULATOR_MEMBERS = {
    "mill": ("start()", "cycle_start()", "run_hooks"),
    "robot": ("set_input()", "output_hooks"),
}


def _emulator_refusal(device: object, kind: MachineKind, faults: Mapping[str, str]) -> str:
    """What ``device``, made by ``kind``'s emulator hook, lacks of its family's emulator
    protocol, in words ("" when it has everything)."""
    from cellctl.emulators.serve import EmulatedDevice

    if not isinstance(device, EmulatedDevice):
        return (
            f"its emulator is a {type(device).__name__}, not an EmulatedDevice "
            "(cellctl.emulators.serve: docs/kinds.md, step 5)"
        )
    needed = [*EMULATOR_MEMBERS[kind.family], *(("set_fault()", "clear_fault()") * bool(faults))]
    missing = []
    for member in needed:
        value = getattr(device, member.removesuffix("()"), None)
        if value is None or (member.endswith("()") and not callable(value)):
            missing.append(member)
        elif member.endswith("_hooks") and not callable(getattr(value, "append", None)):
            missing.append(f"{member} (a list)")
    if missing:
        return (
            f"its emulator ({type(device).__name__}) has no {', '.join(missing)} (a "
            f"{kind.family}'s emulator needs {', '.join(needed)}: docs/kinds.md, step 5)"
        )
    for method in ("start", "cycle_start") if kind.family == "mill" else ():
        if inspect.iscoroutinefunction(getattr(device, method)):
            return (
                f"its emulator's {method}() is async: the emulated cell calls it as a plain "
                f"function (def {method}(self) -> None, not async def)"
            )
    return ""


def _guarded_emulator(kind: MachineKind, who: str) -> Callable[[EmulatorSpec], EmulatedDevice]:
    """A plug-in's emulator hook whose failure is a typed error naming the kind (``emulate
    cell`` then says which, instead of a traceback): the device it makes is held to its
    family's emulator protocol (:data:`EMULATOR_MEMBERS`), and its ``start()`` and
    ``set_fault()`` failing are said in words too."""
    make = kind.emulator

    def guarded(spec: EmulatorSpec) -> EmulatedDevice:
        faults = kind.faults.read() if isinstance(kind.faults, LazyTable) else kind.faults
        try:
            device = make(spec)
        except CellctlError:
            raise
        except Exception as e:  # a plug-in's failure of any kind: said, not a traceback
            raise UsageError(f"{who}: its emulator failed to start: {type(e).__name__}: {e}") from e
        from cellctl.kinds.families import KindContractError

        refusal = _emulator_refusal(device, kind, faults)
        if refusal:
            raise KindContractError(f"{who}: {refusal}")
        if kind.family == "mill":
            _wrap(device, "start", lambda start: _said_start(start, who))
        if faults:
            _wrap(device, "set_fault", lambda set_fault: _checked_set_fault(set_fault, faults, who))
        return device

    return guarded


def _wrap(device: object, method: str, wrap: Callable[[Any], Any]) -> None:
    """``device.method`` replaced by ``wrap(it)`` on the instance: the device stays itself
    (its class, the cell's ``type(device)`` checks)."""
    with contextlib.suppress(AttributeError, TypeError):  # slots, a frozen device: as it is
        setattr(device, method, wrap(getattr(device, method)))


def _said_start(start: Callable[[], object], who: str) -> Callable[[], object]:
    """An emulator's ``start()`` whose failure is said naming the kind."""

    @functools.wraps(start)
    def said() -> object:
        try:
            return start()
        except CellctlError:
            raise
        except Exception as e:  # a plug-in's failure: said, not a traceback
            raise UsageError(f"{who}: its emulator's start() raised {type(e).__name__}: {e}") from e

    return said


def _needed_argument(faults: Mapping[str, str], name: str) -> str:
    """The argument fault switch ``name`` must be given, from its description (``"=MS: ..."``
    -> ``"MS"``), or "" when it takes none or says its default (``"=N: ... (default 5)"``:
    :func:`~cellctl.emulators.switches.default_of`, the one reader of that convention)."""
    from cellctl.emulators.switches import default_of, takes_argument

    if not takes_argument(faults, name) or default_of(faults, name) is not None:
        return ""
    return faults[name][1:].split(":", 1)[0].strip() or "ARG"


def _checked_set_fault(
    set_fault: Callable[[str, str | None], None], faults: Mapping[str, str], who: str
) -> Callable[[str, str | None], None]:
    """A plug-in emulator's ``set_fault`` that refuses a switch given without the argument
    it needs, and says an error other than a UsageError (its contract) in words."""

    @functools.wraps(set_fault)
    def checked(name: str, arg: str | None = None) -> None:
        needed = _needed_argument(faults, name)
        if arg is None and needed:
            raise UsageError(f"fault {name} needs its argument: {name}={needed}")
        try:
            set_fault(name, arg)
        except CellctlError:
            raise
        except Exception as e:  # not a UsageError, as docs/kinds.md asks: said, not raised
            shown = name if arg is None else f"{name}={arg}"
            raise UsageError(
                f"fault {shown}: {who} refused it with {type(e).__name__}: {e} (its set_fault "
                "should raise UsageError in words: docs/kinds.md, step 5)"
            ) from e

    return checked


def _checked_emulated(
    kind: MachineKind, emulated: Callable[[float], dict[str, float]], owner: str
) -> Callable[[float], dict[str, float]]:
    """A plug-in's ``emulated_options`` whose options are checked against its own options
    model as they are made: what an emulated cell writes must pass ``cell check``."""

    def checked(scale: float) -> dict[str, float]:
        broken = f"{owner} is installed but broken: its emulated_options({scale:g})"
        try:
            options = emulated(scale)
        except Exception as e:  # a plug-in's failure of any kind: said, not a traceback
            raise BrokenKind(f"{broken} raised {type(e).__name__}: {e}") from e
        refused = _refused_options(kind, options)
        if refused:
            raise BrokenKind(
                f"{broken} gave options its options model {kind.options.__name__} refuses: "
                f"{refused} (fix emulated_options, or the model)"
            )
        return options

    return checked


def _refused_options(kind: MachineKind, options: object) -> str:
    """What ``kind``'s options model refuses of ``options`` (some of its options: one it
    requires may be missing), in words ("" when nothing)."""
    if not isinstance(options, dict) or not all(isinstance(k, str) for k in options):
        return f"a {type(options).__name__}, not a dict of option -> value"
    try:
        kind.options.model_validate(options)
    except ValidationError as e:
        problems = [
            f"{'.'.join(str(k) for k in item['loc']) or 'options'}: "
            + ("unknown option" if item["type"] == "extra_forbidden" else str(item["msg"]))
            for item in e.errors(include_url=False)
            if item["type"] != "missing"
        ]
        return "; ".join(problems)
    return ""


@cache
def _try(ep: EntryPoint) -> MachineKind | str:
    """The kind entry point ``ep`` declares, or why it gave none (loaded once per process)."""
    try:
        return _load(ep)
    except Exception as e:  # a plug-in's failure of any kind: skip it, say which
        why = str(e) if isinstance(e, _Refused) else f"{type(e).__name__}: {e}"
        log.warning("machine kind %s skipped: %s", ep.name, why)
        return why


def _dist(ep: EntryPoint) -> str:
    """The name of the distribution declaring ``ep``."""
    dist = ep.dist
    if dist is None:
        return "?"
    # Each look at a Distribution's name parses its METADATA again: a sixth of every
    # cellctl's start went there. Kept with the distribution, so its id stays its own.
    known = _DIST_NAMES.get(id(dist))
    if known is None:
        known = _DIST_NAMES[id(dist)] = (dist, dist.name)
    return known[1]


_DIST_NAMES: dict[int, tuple[object, str]] = {}


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
        owner = f"kind {k.name!r} (package {distribution})"
        owned = dataclasses.replace(
            k, origin=Origin(distribution, "tests"), **_owned_tables(k, owner)
        )
        _testing[k.name] = _held_to_contract(owned, f"kind {k.name} (from {distribution})", owner)
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
    """The kind called ``name``; UsageError naming the known ones, or :class:`BrokenKind`
    naming its package and why, for one installed but broken."""
    k = _one(name)
    if isinstance(k, MachineKind):
        return k
    if k:
        dists = sorted({_dist(ep) for ep in _declared().get(name, [])})
        package = f"package{'s' * (len(dists) > 1)} {' and '.join(dists)}"
        raise BrokenKind(f"kind {name!r} ({package}) is installed but broken: {k}")
    raise UsageError(f"unknown machine kind {name!r} (known: {', '.join(names()) or 'none'})")


def family_of(name: str) -> str:
    """The family of kind ``name`` (``robot``, ``mill``)."""
    return kind(name).family


def broken() -> dict[str, str]:
    """Entry points that gave no kind: name -> why."""
    return dict(found().broken)
