"""What a fault is, in the machine's words: one alarm per fault, whoever sees it first.

A fault shows in several places: the monitor's read of an idle machine, the step that was
running on it, a step on another machine that needed it (a transfer opens doors through the
PLC). Each of them names the fault by its cause -- :func:`link_cause` for a link that closed
or went quiet, :func:`status_cause` for a robot whose status says it cannot move -- and the
controller raises the cause's alarm, keeping one active alarm per machine and code
(:meth:`~cellctl.cell.controller.CellController.alarm`): the second sighting adds nothing.
A step's failure is an alarm of its own only when no cause explains it.

Inside ``with blame("plc", "PLC"):`` a link failure is re-raised as :class:`Blamed`, so the
step that called the PLC knows the fault is not its machine's. A request that was under way
when the operator cleared that fault's alarm (a late answer's deadline running out after the
PLC came back) is the same fault: its cause is marked :attr:`Cause.told`, and not raised again.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Final

from cellctl.clock import current_clock
from cellctl.errors import CellctlError, LinkClosed, LinkError, SignalTimeout
from cellctl.kinds.families import Health
from cellctl.protocol.plc import SIGNALS

#: Alarm priorities after ISA-18.2 / IEC 62682, most urgent first.
PRIORITIES: Final = ("high", "medium", "low")
#: Each alarm code's priority, declared once beside the causes that raise them: a stopped
#: cell or a machine's own fault status is high, a machine that does not answer is high (the
#: cell cannot see it), a step that failed or a machine taken out of service is medium, a late
#: pallet is low. A code not listed (a step failure's own code) is :data:`DEFAULT_PRIORITY`.
ALARM_PRIORITY: Final[dict[str, str]] = {
    "estop": "high",
    "status": "high",
    "link": "high",
    "interlock": "medium",
    "out-of-service": "medium",
    "readiness": "medium",
    "initialize": "medium",
    "transfer": "medium",
    "conveyor": "low",
}
DEFAULT_PRIORITY: Final = "medium"


def priority_of(code: str) -> str:
    """The priority of an alarm with ``code`` (see :data:`ALARM_PRIORITY`)."""
    return ALARM_PRIORITY.get(code, DEFAULT_PRIORITY)


#: The alarm of a link the other end closed (a dropped connection, a restarted server).
LINK_CLOSED = "link closed by the other end"


@dataclass(frozen=True)
class Cause:
    """A fault: the machine it is on, its alarm code and its text."""

    machine: str
    code: str
    text: str
    told: bool = False
    """The fault was alarmed, and the alarm cleared, while the failed operation was under
    way: a late sighting of a fault the operator already knows of, not a new one (logged,
    not alarmed again)."""


#: The PLC's emergency stop input pressed: every machine stops (the monitor raises it).
ESTOP = Cause("plc", "estop", "emergency stop: the cell is stopped")


def link_cause(machine: str, label: str, error: BaseException) -> Cause | None:
    """The link fault behind ``error`` (``label`` names the machine in the text: "robot",
    "PLC"); None when the machine answered and the failure is about what it did."""
    if isinstance(error, SignalTimeout):
        return None
    if isinstance(error, LinkClosed):
        return Cause(machine, "link", LINK_CLOSED)
    if isinstance(error, LinkError | TimeoutError | OSError):
        return Cause(machine, "link", f"{label} not answering")
    return None


def read_cause(machine: str, label: str, error: BaseException) -> Cause:
    """A look at an idle machine that failed: its link's fault, or the failure itself."""
    return link_cause(machine, label, error) or Cause(machine, "link", f"{label} failed: {error}")


def door_cause(
    inputs: Mapping[str, bool], doors: Iterable[int], open_: bool, waited: float
) -> Cause | None:
    """A door of ``doors`` (the mills' numbers) the PLC's ``inputs`` show short of its end
    position (open if ``open_``) after ``waited`` s: a stuck door, in the words of an
    interlock wait that ran out ("door of CNC 2 did not open within 120 s"); None if all are
    there. What a step that waited on something else (a robot waiting for the door before
    it goes in) blames when it runs out of time."""
    for n in doors:
        there = f"door_open_{n}" if open_ else f"door_closed_{n}"
        if not inputs.get(there, True):
            signal = SIGNALS[there]
            return Cause("plc", "interlock", f"{signal.not_true} within {waited:g} s")
    return None


def status_cause(machine: str, status: Health) -> Cause:
    """A robot whose machine status shows an error (servo error, power failure, ...)."""
    return Cause(machine, "status", str(status))


class Blamed(CellctlError):
    """A step failed because another machine did: :attr:`cause` says which and how."""

    def __init__(self, cause: Cause, error: BaseException, since: float = 0.0) -> None:
        super().__init__(f"{cause.machine}: {cause.text} ({error})")
        self.cause = cause
        self.since = since
        """When the operation that failed began (``time.time()``)."""


@contextmanager
def blame(machine: str, label: str) -> Iterator[None]:
    """Inside, a link failure or a signal that did not come (a stuck door: code
    ``interlock``) is ``machine``'s: raised again as :class:`Blamed`."""
    since = current_clock().now()
    try:
        yield
    except Blamed:
        raise
    except SignalTimeout as e:
        raise Blamed(Cause(machine, "interlock", str(e)), e, since) from e
    except (CellctlError, OSError) as e:
        cause = link_cause(machine, label, e)
        if cause is None:
            raise
        raise Blamed(cause, e, since) from e
