"""What each library function may do in each host-kept state: the IBM 7545 robot.

The source's library answered every call from the state it kept on the host (spec
``ibm7545-robot.md``, "Library functions and their results"): GO after HALT is "partition
empty" without a byte on the line. The driver consults this table before any byte goes out::

    refusal = robot_refusal(RobotFunction.GO, state=0, partition_full=False)
    if refusal is not None:
        raise DeviceError(refusal.code, refusal.message, detail=refusal.why)

A refusal carries the source's result code and message for that function (the robot's GO:
2 "starting function error", 3 "partition empty"; the mill's DOWNLOAD: 1 "Machine not
initialized", 2 "Absolute zero not set" / "Machine executing program"). Where the source
gives a function no result for a state, the machine's own answer stands in (a robot DOWNLOAD
when uninitialized: reject 48, "improper startup sequence", what the controller says).

Where the host's view cannot be trusted the table allows the call and the machine decides:
the robot says nothing when a program ends, so host state 2 (executing) may be stale, and GO
there goes to the controller (which rejects it with 48 while a cycle runs). DOWNLOAD does not:
the spec's state table has downloads in state 1 only, and the host refuses it in state 2 as
in state 0 (48, "stop the cycle first"; STOP after a program that ended by itself is
harmless and brings the host back to state 1). A mill driver reads CTS first (no byte goes
out) so states 3 and 4 are current when it asks.

No I/O here, no clock: tables and the lookups.
"""

from __future__ import annotations

import enum

from cellctl.protocol.states import ALLOW, Refusal, Rule

__all__ = ["ROBOT_HOST_STATES", "ROBOT_TABLE", "RobotFunction", "robot_refusal"]


# -- the robot ----------------------------------------------------------------------------------


class RobotFunction(enum.StrEnum):
    """The robot's library functions (source names) and the driver's own pieces of them."""

    INITIALIZE = "INITIALIZE"
    RETURN_HOME = "RETURN_HOME"
    AUTOSTART = "AUTOSTART"
    DOWNLOAD = "DOWNLOAD"
    GO = "GO"
    APPLICATION = "APPLICATION"  # select application n (X 3n)
    START_CYCLE = "START_CYCLE"  # X 22 alone
    STOP_CYCLE = "STOP_CYCLE"
    HALT_CYCLE = "HALT_CYCLE"
    MC_STATUS = "MC_STATUS"
    REJECT_STATUS = "REJECT_STATUS"
    DIDO_STATUS = "DIDO_STATUS"
    ERRESET = "ERRESET"


#: Robot states the host keeps (spec "Robot states (kept by the host)").
ROBOT_HOST_STATES = (0, 1, 2)

_STARTING_ERROR = Refusal(2, "starting function error", "robot uninitialized (state 0)")
_PARTITION_EMPTY = Refusal(3, "partition empty", "no program downloaded there since its flush")
_APPLICATION_EMPTY = Refusal(1, "partition empty", "no program downloaded there since its flush")
_IMPROPER_STARTUP = Refusal(
    48, "improper startup sequence", "robot uninitialized (state 0): initialize first"
)
_CYCLE_RUNNING = Refusal(
    48,
    "improper startup sequence",
    "a cycle runs: stop it first (STOP), then download (downloads need state 1)",
)
_GO_RULE = Rule(needs_program=_PARTITION_EMPTY)

#: function -> host state -> rule. State 0: cold start or after HALT (every partition flushed).
ROBOT_TABLE: dict[RobotFunction, dict[int, Rule]] = {
    RobotFunction.INITIALIZE: {0: ALLOW, 1: ALLOW, 2: ALLOW},
    RobotFunction.RETURN_HOME: {0: ALLOW, 1: ALLOW, 2: ALLOW},
    RobotFunction.AUTOSTART: {0: ALLOW, 1: ALLOW, 2: ALLOW},
    RobotFunction.DOWNLOAD: {0: Rule(_IMPROPER_STARTUP), 1: ALLOW, 2: Rule(_CYCLE_RUNNING)},
    # After HALT both apply; the partition speaks first ("3 partition empty", as the source).
    RobotFunction.GO: {
        0: Rule(_STARTING_ERROR, needs_program=_PARTITION_EMPTY),
        1: _GO_RULE,
        2: _GO_RULE,
    },
    RobotFunction.APPLICATION: {
        0: Rule(needs_program=_APPLICATION_EMPTY),
        1: Rule(needs_program=_APPLICATION_EMPTY),
        2: Rule(needs_program=_APPLICATION_EMPTY),
    },
    RobotFunction.START_CYCLE: {0: Rule(_STARTING_ERROR), 1: ALLOW, 2: ALLOW},
    RobotFunction.STOP_CYCLE: {0: ALLOW, 1: ALLOW, 2: ALLOW},
    RobotFunction.HALT_CYCLE: {0: ALLOW, 1: ALLOW, 2: ALLOW},
    RobotFunction.MC_STATUS: {0: ALLOW, 1: ALLOW, 2: ALLOW},
    RobotFunction.REJECT_STATUS: {0: ALLOW, 1: ALLOW, 2: ALLOW},
    RobotFunction.DIDO_STATUS: {0: ALLOW, 1: ALLOW, 2: ALLOW},
    RobotFunction.ERRESET: {0: ALLOW, 1: ALLOW, 2: ALLOW},
}


def robot_refusal(
    function: RobotFunction, state: int, partition_full: bool | None = None
) -> Refusal | None:
    """None if ``function`` may go to the robot in host ``state``, else the source's result.

    ``partition_full``: whether the host's view has a program in the partition the call names
    (GO, APPLICATION); ignored by functions that name none.
    """
    rule = ROBOT_TABLE[function].get(state, ALLOW)
    if rule.needs_program is not None and partition_full is False:
        return rule.needs_program
    return rule.refusal
