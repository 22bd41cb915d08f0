"""The Dyna 2400 driver's records: its state tables, results and status.

:class:`~cellctl.kinds.dyna2400.driver.Dyna2400Mill` returns a :class:`Result` (code 0 and
the source's message), raises :class:`MillInputError` for a refused file, and reports a
:class:`MillStatus`; a download keeps a :class:`BlockTiming` per block and reports
:data:`Progress`. Import them from here or, as before, from the driver::

    status = await mill.status()
    status.shown            # "Downloaded, active, executing" (a block is running)
    status.kind_condition   # Condition.BUSY
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from cellctl.errors import DeviceError, UsageError
from cellctl.kinds import Condition
from cellctl.kinds.dyna2400.options import MillState
from cellctl.kinds.families import RunNotStarted, RunProgress

#: Machine states in words.
MILL_STATES = {int(s): s.text for s in MillState}
#: States in which a block or a GO program runs.
RUNNING = frozenset({MillState.DOWNLOADED, MillState.GO})
#: The condition each mill state shows on every surface.
MILL_CONDITIONS: dict[int, Condition] = {
    MillState.NOT_READY: Condition.NOT_READY,
    MillState.READY: Condition.NOT_READY,
    MillState.INITIALIZED: Condition.IDLE,
    MillState.DOWNLOADED: Condition.BUSY,
    MillState.GO: Condition.BUSY,
}
INITIALIZE_RESULTS = {
    0: "Initializing was correct",
    1: "Machine already initialized",
    2: "Machine code error",
    3: "Forcing function error",
    4: "Machine not ready",
    5: "Initializing file error",
}
DOWNLOAD_RESULTS = {
    0: "Download was correct",
    1: "Machine not initialized",
    2: "Absolute zero not set / Machine executing program",
    3: "Machine code error",
    4: "File not found",
    5: "Not a valid program",
}
END_RESULTS = {0: "Ending was correct", 1: "Machine code error", 2: "Could not open file"}
REFERENCE_ZERO_NOT_SET = "reference zero not set"
EXECUTING = "executing"


class MillRefused(DeviceError, RunNotStarted):
    """A function the host's state or the mill's CTS refuses before a byte goes out (the
    spec's refusals: not initialized, machine executing): a cell's run that ends so started
    nothing, its part as it was."""


class MillInputError(UsageError):
    """A program or setup file refused before any byte went out: ``code`` is the spec's result
    (download 4 file not found, 5 not a valid program; initialize 5 file error), ``problems``
    the validator's findings."""

    def __init__(
        self, code: int, message: str, detail: str, problems: Sequence[object] = ()
    ) -> None:
        self.code = code
        self.message = message
        self.problems = list(problems)
        super().__init__(f"{message} (code {code}): {detail}")


@dataclass(frozen=True)
class Result:
    """A successful call: code 0 and the source's message."""

    code: int
    message: str


@dataclass(frozen=True)
class MillStatus:
    """What ``status()`` reports: the state, its special condition, and CTS."""

    state: int
    ready: bool  # CTS high
    condition: str | None = None  # REFERENCE_ZERO_NOT_SET or EXECUTING
    initialized: bool = False  # its setup program went out since the last END

    @property
    def set_up(self) -> bool:
        """Initialized and idle (state 2), whatever CTS says."""
        return self.state == MillState.INITIALIZED

    @property
    def takes_work(self) -> bool:
        """State 2 with CTS high: a program may go out now."""
        return self.ready and self.set_up

    @property
    def awaiting_operator(self) -> bool:
        """The setup went out; the operator has yet to set the reference zero (state 1)."""
        return self.state == MillState.READY and not self.ready and self.initialized

    @property
    def waiting_for(self) -> str | None:
        return self.condition

    @property
    def state_text(self) -> str:
        return MILL_STATES.get(self.state, f"state {self.state}")

    @property
    def host_text(self) -> str:
        """The state as the host knows it without a byte sent: after a successful INITIALIZE
        the mill waits for its operator (state 1 until NEXT), which is said so, not as the
        "Uninitialized" of a mill never set up."""
        if self.awaiting_operator:
            return f"{INITIALIZE_RESULTS[0]}: {REFERENCE_ZERO_NOT_SET}, press NEXT"
        return self.state_text

    @property
    def shown(self) -> str:
        """The state in the machine's words, with its special condition."""
        return self.state_text + (f", {self.condition}" if self.condition else "")

    @property
    def kind_condition(self) -> Condition:
        """The condition this status shows on every surface (an initialized mill without
        CTS waits for its operator's reference zero: not ready)."""
        if self.state == MillState.INITIALIZED and not self.ready:
            return Condition.NOT_READY
        return MILL_CONDITIONS.get(self.state, Condition.NOT_READY)

    def __str__(self) -> str:
        extra = f", {self.condition}" if self.condition else ""
        cts = "high" if self.ready else "low"
        return f"state {self.state} ({self.state_text}{extra}; CTS {cts})"


#: Where a download stands; passed to the progress callback after every line.
Progress = RunProgress


@dataclass
class BlockTiming:
    """One block of a download: bytes, when sending began, when taken (CTS low), when done."""

    block: int
    bytes: int
    lines: int
    started: float
    taken: float = 0.0
    done: float = 0.0

    @property
    def transfer_s(self) -> float:
        return self.taken - self.started

    @property
    def machining_s(self) -> float:
        return self.done - self.taken if self.done else 0.0


ProgressCallback = Callable[[Progress], None]
