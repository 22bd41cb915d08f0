"""The conditions a machine can be in, for every family and kind, and its last error.

Each kind maps its own states onto :class:`Condition` (the robot's host state 2 and a mill's
state 3 are both ``BUSY``); the controller adds what only it knows (``OUT_OF_SERVICE``). The
status model carries the condition, so a surface colours a card or a stack light by field::

    if machine.condition is Condition.ALARM: ...
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


class Condition(enum.StrEnum):
    """What a machine is doing, in the words every surface shares."""

    OFFLINE = "offline"
    """Not connected, or not answering: nothing is known of it now."""
    NOT_READY = "not-ready"
    """Answering, but it needs initializing or its setup before it takes work."""
    IDLE = "idle"
    """Ready for work."""
    BUSY = "busy"
    """Running a program, a download or a cut."""
    ALARM = "alarm"
    """It reports a fault of its own (a status bit, an emergency stop)."""
    OUT_OF_SERVICE = "out-of-service"
    """Taken out of automatic service (by the operator, or after repeated faults)."""


@dataclass(frozen=True)
class LastError:
    """A machine's last error: the source's or the machine's ``code`` where it has one, and
    the ``text`` in the user's words."""

    text: str
    code: int | None = None

    @classmethod
    def of(cls, error: BaseException) -> LastError:
        """The last error an exception tells: a machine's code where it gave one."""
        code = getattr(error, "code", None)
        return cls(str(error) or type(error).__name__, code if isinstance(code, int) else None)
