"""The faults a plan may put on a machine, checked before anything runs::

    switches(kind)                                # ("down", and its emulator's switches)
    check_switch("plc", None, "stuck-door", "abc")  # UsageError: stuck-door needs a mill ...

``down`` is the plan's own (the machine out of service). Every other name is one of the
machine's emulator fault switches: its kind's table (the registry's), the PLC's for ``plc``.
A switch's argument is checked by the emulator itself: :func:`check_switch` switches it on
in a fresh emulator of the machine's kind, nowhere connected and then dropped, so a plan
takes exactly what ``cellctl emulate cell --fault MACHINE:NAME[=ARG]`` takes, in the same
words, and no second table of arguments can drift from the emulators'.
"""

from __future__ import annotations

from typing import Any, Final

from cellctl.errors import UsageError

#: The fault that takes a machine out of service (not an emulator's switch).
DOWN: Final = "down"
#: The machine name of the cell's PLC in a fault window.
PLC: Final = "plc"


def switches(kind: str | None) -> tuple[str, ...]:
    """The faults a plan may put on a machine of ``kind`` (None: the PLC): ``down`` (not the
    PLC's) and its emulator's fault switches. An unknown kind has only ``down``."""
    from cellctl.kinds import registry

    if kind is None:
        from cellctl.emulators.plc import FAULTS

        return tuple(FAULTS)
    found = tuple(registry.kind(kind).faults) if kind in registry.names() else ()
    return (DOWN, *found)


def check_switch(machine: str, kind: str | None, name: str, arg: str | None) -> None:
    """Refuse ``name`` (with ``arg``) on ``machine`` of ``kind`` (None: the PLC) unless its
    emulator takes it: an unknown name with the names known, a bad argument in the
    emulator's own words (:class:`UsageError`)."""
    known = switches(kind)
    if name not in known:
        raise UsageError(f"fault {name!r} on {machine}: unknown (known: {', '.join(known)})")
    if name == DOWN:
        if arg is not None:
            raise UsageError(f"fault down on {machine}: it takes no argument, not {arg!r}")
        return
    try:
        _fresh_emulator(kind).set_fault(name, arg)
    except UsageError as e:
        shown = name if arg is None else f"{name}={arg}"
        raise UsageError(f"fault {machine}:{shown}: {e}") from None


def _fresh_emulator(kind: str | None) -> Any:
    """An emulator of ``kind`` (None: the PLC) as the plan's emulated cell builds it, not
    started: switching a fault on in it only checks the switch and its argument."""
    if kind is None:
        from cellctl.emulators.plc import PlcEmulator

        return PlcEmulator()
    from cellctl.kinds import registry
    from cellctl.kinds.kind import EmulatorSpec

    return registry.kind(kind).emulator(EmulatorSpec())


__all__ = ["DOWN", "PLC", "check_switch", "switches"]
