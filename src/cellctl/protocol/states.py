"""What a library function may do in a machine's host-kept state: the shape of a kind's table.

Each kind with a library like the source's keeps one table of :class:`Rule` per function and
host state, and its driver consults it before any byte goes out::

    refusal = robot_refusal(RobotFunction.GO, state=0, partition_full=False)
    if refusal is not None:
        raise DeviceError(refusal.code, refusal.message, detail=refusal.why)

No I/O here, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ALLOW", "Refusal", "Rule"]


@dataclass(frozen=True)
class Refusal:
    """A function refused in a state: the source's result ``code`` and ``message``."""

    code: int
    message: str
    why: str = ""


@dataclass(frozen=True)
class Rule:
    """One cell of a table: allowed (``refusal`` None) or refused; ``needs_program``: refused
    with it first when the partition named in the call holds no program."""

    refusal: Refusal | None = None
    needs_program: Refusal | None = None


ALLOW = Rule()
