"""The iso-cnc host's states and its status record (the mill family's :class:`MillReading`)::

status = cnc.host_status()
status.shown            # "drip-feeding 4210/10000 chars, stalled 0.4 s"
status.kind_condition   # Condition.BUSY
"""

from __future__ import annotations

from dataclasses import dataclass

from cellctl.kinds.condition import Condition
from cellctl.kinds.kind import MachineState


class IsoCncState(MachineState):
    """What the host is doing with the control."""

    IDLE = 0, "idle"
    READING = 1, "reading"
    PUNCHING = 2, "punching"
    DRIP_FEEDING = 3, "drip-feeding"
    ALARM = 4, "alarm"


CONDITIONS: dict[IsoCncState, Condition] = {
    IsoCncState.IDLE: Condition.IDLE,
    IsoCncState.READING: Condition.BUSY,
    IsoCncState.PUNCHING: Condition.BUSY,
    IsoCncState.DRIP_FEEDING: Condition.BUSY,
    IsoCncState.ALARM: Condition.ALARM,
}


@dataclass(frozen=True)
class IsoCncStatus:
    """The host's view of one control: its state, a transfer's progress, the last alarm."""

    state: IsoCncState = IsoCncState.IDLE
    chars_sent: int = 0
    chars_total: int = 0
    stall_s: float = 0.0
    alarm: int | None = None
    alarm_text: str = ""

    @property
    def shown(self) -> str:
        text = self.state.text
        if self.state == IsoCncState.ALARM and self.alarm is not None:
            return f"alarm {self.alarm:03d} {self.alarm_text}".rstrip()
        if self.chars_total and self.state != IsoCncState.IDLE:
            text += f" {self.chars_sent}/{self.chars_total} chars"
        if self.stall_s:
            text += f", stalled {self.stall_s:.1f} s"
        return text

    @property
    def kind_condition(self) -> Condition:
        return CONDITIONS[self.state]

    @property
    def ready(self) -> bool:
        return self.state == IsoCncState.IDLE

    @property
    def set_up(self) -> bool:
        return self.state != IsoCncState.ALARM

    @property
    def takes_work(self) -> bool:
        return self.state == IsoCncState.IDLE

    @property
    def awaiting_operator(self) -> bool:
        return False

    @property
    def waiting_for(self) -> str | None:
        return None

    def __str__(self) -> str:
        return self.shown
