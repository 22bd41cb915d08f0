"""What the IBM 7545's declaration needs without its driver: its options (``cell.toml``),
its host states and the condition each shows (the registry reads these at start; the driver
is imported when a robot is opened)."""

from __future__ import annotations

from typing import Annotated

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    NonNegativeFloat,
    NonNegativeInt,
    PositiveFloat,
)

from cellctl.kinds.condition import Condition
from cellctl.kinds.ibm7545.records import ExecuteOperand
from cellctl.kinds.kind import MachineState


class RobotState(MachineState):
    """Robot states the host keeps (spec: "Robot states (kept by the host)")."""

    UNINITIALIZED = 0, "Uninitialized"
    INITIALIZED = 1, "Initialized (auto mode)"
    EXECUTING = 2, "Executing"


#: Robot states in words.
ROBOT_STATES = {int(s): s.text for s in RobotState}
#: The condition each host state shows on every surface.
ROBOT_CONDITIONS: dict[int, Condition] = {
    RobotState.UNINITIALIZED: Condition.NOT_READY,
    RobotState.INITIALIZED: Condition.IDLE,
    RobotState.EXECUTING: Condition.BUSY,
}


def robot_condition(state: int, ok: bool = True) -> Condition:
    """The condition of a robot in host ``state`` whose status bytes say ``ok`` or not."""
    return ROBOT_CONDITIONS.get(state, Condition.NOT_READY) if ok else Condition.ALARM


class RobotConfig(BaseModel):
    """Deadlines and assumed values; every one can be set per robot (``cell.toml`` options)."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    reply_timeout: PositiveFloat = 2.0
    """Seconds the controller may take to start answering (beyond the wire time)."""
    busy_silence: PositiveFloat = 30.0
    """Seconds of silence tolerated while the controller is busy (it repeats Xoff every ~25 s)."""
    busy_ceiling: PositiveFloat = 300.0
    """Seconds a busy controller may keep the host waiting in all (return home, a long stop)."""
    checksum_retries: NonNegativeInt = 3
    """Times a read with a bad D-record checksum (or a garbled handshake) is repeated."""
    download_retries: NonNegativeInt = 3
    """Times a download refused for a transmission error is sent again from its N record."""
    retry_settle: NonNegativeFloat = 0.2
    """Seconds of quiet line awaited (input discarded) before a retry."""
    erreset_operand: Annotated[int, Field(ge=0, le=255)] = int(ExecuteOperand.ERRESET)
    """ERRESET's operand: not in the source, **assumed** 24."""
