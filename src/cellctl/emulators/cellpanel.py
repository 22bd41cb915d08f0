"""The emulated cell's hand commands: what an operator does at a machine of the cell, typed on
the standard input of ``cellctl emulate cell --panel``, one a line::

    clear cnc1      the operator's reset at cnc1: an error condition it keeps is cleared
                    (a Dyna 2400's ERROR: memory cleared, its link mode selected again, READY;
                    an ISO control's alarm: RESET)
    show            each machine's display (a Dyna 2400's: READY, RUN, ERROR ...; an ISO
                    control's: ALARM 086 DR OFF, RMT reading ...)
    help            these commands

The words are the Dyna 2400 panel's (``cellctl emulate mill --manual``: ``clear``, ``show``),
followed by the machine, as the cell's names go. ``clear`` is the machine's kind's own
reset (the emulators' :meth:`~cellctl.emulators.serve.EmulatedDevice.operator_clear`, which a
plan's operator calls too): a machine whose kind keeps no error condition has nothing to
clear, and a block running is left alone (its end is its READY). The answer says what the
machine shows after it, never a reset it did not see: an alarm whose cause is still there
(an ISO control's DR still off) is still shown.

Each command answers one line (:func:`hand_command`); one the panel does not know is
refused with the commands it knows (:class:`~cellctl.errors.UsageError`).
"""

from __future__ import annotations

from typing import Any, Final

from cellctl.errors import UsageError

__all__ = ["HAND_COMMANDS", "hand_command"]

#: The hand commands, for ``--help`` and the refusal of an unknown one.
HAND_COMMANDS: Final = (
    "clear MACHINE (the operator's reset at the machine: a Dyna 2400's ERROR cleared, "
    "READY again; an ISO control's alarm RESET), show (each machine's display), help"
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


def _display(device: Any) -> str | None:
    """What the machine's display shows, if its emulator has one (the Dyna 2400's, an ISO
    control's)."""
    shown = getattr(device, "display", None)
    return shown if isinstance(shown, str) else None
