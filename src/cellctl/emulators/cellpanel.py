"""The emulated cell's hand commands: what an operator does at a machine of the cell, typed on
the standard input of ``cellctl emulate cell --panel``, one a line::

    clear cnc1      the operator's reset at cnc1: an error condition it keeps is cleared
                    (a Dyna 2400's ERROR: memory cleared, its link mode selected again, READY;
                    an ISO control's alarm: RESET)
    show            each machine's display (a Dyna 2400's: READY, RUN, ERROR ...; an ISO
                    control's: ALARM 086 DR OFF, RMT reading ...)
    fault cnc2:never-ready
                    a fault switch on now, checked as ``--fault MACHINE:NAME[=ARG]`` is, in
                    the same words: an instructor pulls a cable mid-run
    fault off cnc2:never-ready
                    the switch off, then what the machine's operator does after it (its
                    emulator's ``operator_after``, as the test rig and a plan's operator do)
    faults          each machine's switches on now, and the switches it has
    help            these commands

The words are the Dyna 2400 panel's (``cellctl emulate mill --manual``: ``clear``, ``show``),
followed by the machine, as the cell's names go. ``clear`` is the machine's kind's own
reset (the emulators' :meth:`~cellctl.emulators.serve.EmulatedDevice.operator_clear`, which a
plan's operator calls too): a machine whose kind keeps no error condition has nothing to
clear, and a block running is left alone (its end is its READY). The answer says what the
machine shows after it, never a reset it did not see: an alarm whose cause is still there
(an ISO control's DR still off) is still shown.

A switch whose argument may be left out says the value it then took (``fault cnc1:drop``:
"cnc1: drop on (5 lines, its default)"), from its description in the fault table
(:func:`~cellctl.emulators.switches.default_of`); ``emulate cell --fault`` says the same at
start (:func:`switch_on`).

Each command answers one line (:func:`hand_command`); one the panel does not know is
refused with the commands it knows (:class:`~cellctl.errors.UsageError`).
"""

from __future__ import annotations

from collections.abc import Mapping
from collections.abc import Set as AbstractSet
from typing import Any, Final

from cellctl.emulators.switches import check_fault, said_on, shown_switch, split_fault
from cellctl.errors import CellctlError, UsageError

__all__ = ["HAND_COMMANDS", "hand_command", "switch_on"]

#: The hand commands, for ``--help`` and the refusal of an unknown one.
HAND_COMMANDS: Final = (
    "clear MACHINE (the operator's reset at the machine: a Dyna 2400's ERROR cleared, "
    "READY again; an ISO control's alarm RESET), show (each machine's display), "
    "fault MACHINE:NAME[=ARG] (a fault switch on now, checked as --fault is), "
    "fault off MACHINE:NAME (the switch off, then the operator's steps after it), "
    "faults (each machine's switches on now, and those it has), help"
)


async def hand_command(cell: Any, text: str) -> str:
    """Do hand command ``text`` on ``cell`` (an :class:`~cellctl.emulators.cell.EmulatedCell`)
    and say what the machine shows after it ("" for a blank line)."""
    words = text.split()
    if not words:
        return ""
    key, args = words[0].lower(), words[1:]
    if key == "clear" and len(args) == 1:
        return await _clear(cell, args[0])
    if key == "show" and not args:
        return "; ".join(f"{name}: {_display(m) or 'no display'}" for name, m in _machines(cell))
    if key == "fault" and len(args) == 1:
        return switch_on(cell, args[0])
    if key == "fault" and len(args) == 2 and args[0].lower() == "off":
        return await _switch_off(cell, args[1])
    if key == "faults" and not args:
        return _faults(cell)
    if key == "help" and not args:
        return f"hand commands: {HAND_COMMANDS}"
    raise UsageError(f"unknown hand command {text.strip()!r}: {HAND_COMMANDS}")


def _machines(cell: Any) -> list[tuple[str, Any]]:
    """The cell's machines an operator stands at (the robot, the mills), by their names."""
    return [(cell.robot_name, cell.robot), *cell.mills.items()]


async def _clear(cell: Any, name: str) -> str:
    # Here, not at the top: `cellctl --help` names the hand commands, and serves nothing.
    from cellctl.emulators.serve import EmulatedDevice

    machines = dict(_machines(cell))
    device = machines.get(name)
    if device is None:
        raise UsageError(f"clear {name}: no machine {name!r} ({', '.join(machines)})")
    if type(device).operator_clear is EmulatedDevice.operator_clear:
        # Its kind keeps no error condition a reset at the machine clears (a UR's are the
        # pendant's, after a fault): nothing was done, and nothing is said to have been.
        return f"{name}: nothing to reset at the machine (its kind keeps no error condition)"
    before = _display(device)
    await device.operator_clear()
    after = _display(device)
    if getattr(device, "alarmed", False) is True:  # what it shows, not what was pressed
        return (
            f"{name}: not cleared: it still shows {after or 'an alarm'} (its cause is still "
            "there: see to it, then clear again)"
        )
    if before is None:  # a kind without a display: its own reset ran, nothing shows it
        return f"{name}: its operator's reset done (it has no display to show the result)"
    if after == before:
        return f"{name}: nothing to clear ({before})"
    return f"{name}: {before} cleared: {after}"


def switch_on(cell: Any, text: str, *, at_start: bool = False) -> str:
    """Switch fault ``text`` (``MACHINE:NAME[=ARG]``) on at ``cell`` now and say what was
    switched on: ``"cnc1: drop on (5 lines, its default)"``. Checked as ``emulate cell
    --fault`` checks it, in the same words (:func:`~cellctl.emulators.switches.check_fault`,
    then the machine's emulator).

    ``at_start``: given as the cell starts. A mill's fault that acts as a block ends
    (:data:`~cellctl.emulators.cell.CUT_FAULTS`) then waits for the mill's first cut, as a
    stall in the middle of a cut comes: on at once, it would take the setup block, the first
    the mill runs. From the panel it is on at once (the next block the mill runs)."""
    tables = cell.fault_tables()
    machine, name, arg = check_fault(text, tables)
    said = said_on(machine, name, arg, tables[machine])
    if at_start and machine in cell.mills:
        # Here, not at the top: `cellctl --help` names the hand commands, and serves nothing.
        from cellctl.emulators.cell import CUT_FAULTS

        if name in CUT_FAULTS:
            cell.switch_on_at_cut(machine, name, arg)
            return f"{said} as its first cut starts"
    cell.set_fault(_own_name(cell, machine), name, arg)
    return said


async def _switch_off(cell: Any, text: str) -> str:
    """``fault off MACHINE:NAME``: the switch off and the operator's steps after it (its
    emulator's ``operator_after``), what the test rig and a plan's operator do."""
    machine, name, arg = split_fault(text)
    if arg is not None:
        raise UsageError(
            f"fault off {text}: write fault off MACHINE:NAME, without =ARG (a switch goes "
            "off whatever it took)"
        )
    machine, name, _ = check_fault(f"{machine}:{name}", cell.fault_tables())
    device = cell.machine(_own_name(cell, machine))
    on = _on_now(device, {})
    if on is not None and name not in on:
        # Never on, or gone by itself once it acted (a dropped line): the operator's steps
        # after a fault would only disturb a machine that has none.
        return f"{machine}: {name} is not on (nothing switched off)"
    device.clear_fault(name)
    try:
        await device.operator_after(name)
    except CellctlError as e:
        # The switch is off all the same: said so, with what the operator could not do (a
        # controller still powering on has no link mode to select yet).
        return f"{machine}: {name} off; the operator's steps after it refused: {e}"
    shown = _display(device)
    return f"{machine}: {name} off" + ("" if shown is None else f"; it shows {shown}")


def _faults(cell: Any) -> str:
    """``faults``: each machine's switches on now (as its emulator keeps them), and the
    switches it has (its table)."""
    tables = cell.fault_tables()
    said = []
    for name, device in [*_machines(cell), ("plc", cell.plc)]:
        table = tables[name]
        on = _on_now(device, table)
        now = (
            "what is on cannot be read"
            if on is None
            else f"{', '.join(on.values()) or 'nothing'} on"
        )
        said.append(f"{name}: {now} (its switches: {', '.join(table) or 'none'})")
    return "; ".join(said)


def _on_now(device: Any, table: Mapping[str, str]) -> dict[str, str] | None:
    """The switches on at ``device`` now, each as shown (``"drop=3"``, ``"slow (400 ms, its
    default)"``), from its emulator's ``faults`` (name -> argument, or a set of names); None
    for an emulator that keeps none to read (a plug-in's need not)."""
    faults = getattr(device, "faults", None)
    if isinstance(faults, Mapping):
        return {
            str(n): shown_switch(table, str(n), None if a is None else str(a))
            for n, a in faults.items()
        }
    if isinstance(faults, AbstractSet):  # names only: its arguments are not kept to show
        return {str(n): str(n) for n in sorted(faults, key=str)}
    return None


def _own_name(cell: Any, machine: str) -> str:
    """The cell's name of ``machine`` as a fault names it (``robot``: the robot's)."""
    return cell.robot_name if machine == "robot" and machine not in cell.mills else machine


def _display(device: Any) -> str | None:
    """What the machine's display shows, if its emulator has one (the Dyna 2400's, an ISO
    control's)."""
    shown = getattr(device, "display", None)
    return shown if isinstance(shown, str) else None
