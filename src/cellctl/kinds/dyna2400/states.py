"""What each DYNALAN library function may do in each host-kept state of a Dyna 2400 mill.

The source's library answered every call from the state it kept on the host (spec
``dyna2400-cnc.md``, "Library functions and their results"): a DOWNLOAD before INITIALIZE is
"Machine not initialized" without a byte on the line. A mill driver reads CTS first (no byte
goes out) so states 3 and 4 are current when it asks. No I/O here, no clock.
"""

from __future__ import annotations

import enum

from cellctl.protocol.states import ALLOW, Refusal, Rule

__all__ = ["MILL_HOST_STATES", "MILL_TABLE", "MillFunction", "mill_host_state", "mill_refusal"]


# -- the mill -------------------------------------------------------------------------------------


class MillFunction(enum.StrEnum):
    """The mill's library functions (source names) and the link operations beside them."""

    INITIALIZE = "INITIALIZE"  # forcing function 1: normal
    INITIALIZE_FORCE = "INITIALIZE_FORCE"  # forcing function 2: after a machine failure
    DOWNLOAD = "DOWNLOAD"
    ENDLOAD = "ENDLOAD"
    STATUS = "STATUS"
    GO = "GO"
    LOAD = "LOAD"  # program load (at most 900 lines, not run)
    LINE_EXECUTE = "LINE_EXECUTE"
    UPLOAD = "UPLOAD"


#: Host states of a mill (spec "Machine states"). State 1 is two states for the host: the
#: controller shows READY but was never set up (``"1"``), or the setup program went and the
#: operator has not yet set the reference zero and pressed NEXT (``"1 setup"``).
MILL_HOST_STATES = ("0", "1", "1 setup", "2", "3", "4")


def mill_host_state(state: int, initialized: bool) -> str:
    """The table's column for a mill in ``state`` (0-4) that was or was not initialized."""
    if state == 1 and initialized:
        return "1 setup"
    return str(state)


_NOT_INITIALIZED = Refusal(1, "Machine not initialized", "INITIALIZE it first")
_ZERO_NOT_SET = Refusal(2, "Absolute zero not set", "the operator has not pressed NEXT yet")
_EXECUTING = Refusal(2, "Machine executing program", "a block is executing (CTS low)")
_ALREADY = Refusal(1, "Machine already initialized", "force (2) after a machine failure")


def _row(**cells: Rule) -> dict[str, Rule]:
    row = dict.fromkeys(MILL_HOST_STATES, ALLOW)
    row.update({k.replace("_", " ").removeprefix("s"): v for k, v in cells.items()})
    return row


_EXEC = Rule(_EXECUTING)

#: function -> host state -> rule. A forced INITIALIZE is the way out of any state.
MILL_TABLE: dict[MillFunction, dict[str, Rule]] = {
    MillFunction.INITIALIZE: _row(
        s1_setup=Rule(_ALREADY), s2=Rule(_ALREADY), s3=Rule(_ALREADY), s4=Rule(_ALREADY)
    ),
    MillFunction.INITIALIZE_FORCE: _row(),
    MillFunction.DOWNLOAD: _row(
        s0=Rule(_NOT_INITIALIZED),
        s1=Rule(_NOT_INITIALIZED),
        s1_setup=Rule(_ZERO_NOT_SET),
        s3=_EXEC,
        s4=_EXEC,
    ),
    MillFunction.ENDLOAD: _row(s3=_EXEC, s4=_EXEC),
    MillFunction.STATUS: _row(),
    MillFunction.GO: _row(s3=_EXEC, s4=_EXEC),
    MillFunction.LOAD: _row(s3=_EXEC, s4=_EXEC),
    MillFunction.LINE_EXECUTE: _row(s3=_EXEC, s4=_EXEC),
    MillFunction.UPLOAD: _row(),
}


def mill_refusal(function: MillFunction, state: int, initialized: bool) -> Refusal | None:
    """None if ``function`` may go to the mill in host ``state``, else the source's result."""
    return MILL_TABLE[function][mill_host_state(state, initialized)].refusal
