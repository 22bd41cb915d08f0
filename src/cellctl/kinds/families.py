"""The families the cell works with: :class:`Robot` and :class:`Mill`.

The controller talks to a machine through its family's protocol, never a kind's class: a
kind's driver implements one of these. The route names programs; the kind knows how to get
them onto its machine (a robot's partitions, a mill's blocks)::

    slot = await robot.ensure_program("cnc1_to_cnc2", program, progress)
    await robot.start(slot)
    await robot.wait_end(done_output=6, timeout=120, poll=0.02)

    await mill.setup(Path("cnc1_setup.dyn"), force=True)
    await mill.run(Path("base_rough.dyn"), progress=on_progress)
    status = await mill.status()           # status.takes_work, status.kind_condition
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from cellctl.drivers.base import CallbackOutput, StartOutput
from cellctl.errors import CellctlError, DeviceError, UsageError
from cellctl.kinds.condition import Condition
from cellctl.link import Link

__all__ = [
    "CallbackOutput",
    "CycleAborted",
    "Health",
    "HostStatus",
    "KindContractError",
    "Mill",
    "MillReading",
    "Robot",
    "RunNotStarted",
    "RunProgress",
    "StartOutput",
    "checked_driver",
    "nothing_started",
    "setup_lost",
]


@dataclass(frozen=True)
class HostStatus:
    """A machine's state as the host keeps it (no byte sent): its words and condition."""

    text: str
    condition: Condition


class Health(Protocol):
    """A robot's own status read from the machine: ``ok``, and its words (``str()``)."""

    @property
    def ok(self) -> bool: ...


class CycleAborted(DeviceError):
    """A running program was aborted by the machine itself (power failure, servo error):
    :attr:`status` is the machine's status that says why."""

    def __init__(self, status: Health, detail: str, code: int = 0) -> None:
        super().__init__(code, str(status), detail=detail)
        self.status = status


class RunNotStarted(CellctlError):
    """A mill's ``run()`` failed before anything of the program reached the machine: the
    part is as it was, and the cell may run the program on it again.

    The cell never runs a program twice on a part that may have been cut: once ``run()`` was
    called, any failure holds the part for inspection unless the kind says positively that
    nothing started, by raising this (or an error class that also derives from it, such as
    ``class NotReady(DeviceError, RunNotStarted)``) or a :class:`~cellctl.errors.UsageError`
    (refused before any byte), and reported no progress but ``"waiting"`` before it."""


def nothing_started(error: BaseException, phases: Iterable[str] = ()) -> bool:
    """True if a mill's ``run()`` that failed with ``error``, having reported progress in
    ``phases``, says positively that nothing of the program went out (see
    :class:`RunNotStarted`): any phase but ``"waiting"`` counts as started."""
    if any(phase != "waiting" for phase in phases):
        return False
    return isinstance(error, RunNotStarted | UsageError)


@dataclass
class RunProgress:
    """Where a program run stands; passed to the progress callback as it goes on."""

    block: int
    blocks: int
    lines_sent: int
    lines_total: int
    bytes_sent: int
    bytes_total: int
    # "waiting" (for the machine: nothing went out yet), "sending", "machining", "done"; the
    # cell counts any phase but "waiting" as the part's cut begun (see RunNotStarted).
    phase: str
    # The run's own estimate (the program's preview: its line time and cut time), corrected
    # by the machine's reports: ``estimate_done_s`` of ``estimate_s`` were done at ``at``
    # (time.time()); while ``running`` the machine works on, so the figure grows with the
    # clock, but never past ``estimate_cap_s`` (the end of what it works on now) before the
    # machine says it is done. ``estimate_s`` 0: no estimate.
    estimate_s: float = 0.0
    estimate_done_s: float = 0.0
    estimate_cap_s: float = 0.0
    at: float = 0.0
    running: bool = False


#: The most of its estimate a run shows done while the machine still works on it.
RUNNING_AT_MOST = 0.99


def estimated_done(progress: Mapping[str, Any], now: float) -> float | None:
    """Seconds of a run's estimate done at ``now`` (:class:`RunProgress`'s ``estimate_*``
    fields, or the same keys of its dict): what was done at its report, plus the time since
    while the machine runs, never past the cap; None without an estimate."""
    total = float(progress.get("estimate_s") or 0.0)
    if total <= 0:
        return None
    done = float(progress.get("estimate_done_s") or 0.0)
    if progress.get("running"):
        cap = float(progress.get("estimate_cap_s") or done)
        done = min(max(done, cap), done + max(0.0, now - float(progress.get("at") or now)))
        # Never "100 %" while the machine works: only its own report ends the run.
        return min(done, RUNNING_AT_MOST * total)
    return min(done, total)


RecordsProgress = Callable[[int, int, int], None]


# -- models for bounds from physics (pure: no I/O, no clock) ------------------------------------


@dataclass
class ProgramRun:
    """One run of a robot program on its kind's motion model: when it reached its end, what
    it wrote and when, where the arm stopped (a kind's own point type)."""

    end_s: float = 0.0
    position: Any = None
    motion_s: float = 0.0  # the arm's own work: moves, gripper, delays
    wait_s: float = 0.0  # waiting for inputs
    writes: list[tuple[float, int, bool]] = field(default_factory=list)  # (time, port, value)

    def first_write(self, port: int, value: bool) -> float | None:
        """When output ``port`` was first set to ``value``; None if never."""
        return next((t for t, p, v in self.writes if p == port and v == value), None)


#: ``input_ready(port, value, now, run)``: the time (s), ``now`` or later, at which input
#: ``port`` has ``value``; ``run`` is the run so far (what the program wrote, and when).
InputReady = Callable[[int, bool, float, ProgramRun], float]


class RobotModel(Protocol):
    """A robot kind's motion model, in machine seconds (the cell's physical bound runs it)."""

    def starts(self, programs: Iterable[Any]) -> list[Any]:
        """Where a program may start: home, or where any of ``programs`` leaves the arm."""
        ...

    def run(self, program: Any, *, input_ready: InputReady, start: Any) -> ProgramRun:
        """Run ``program`` (as the cell's config holds it) from ``start`` to its end."""
        ...

    def download_chars(self, program: Any) -> int:
        """Characters on the line, both ways, for one download of ``program``."""
        ...


class MillModel(Protocol):
    """A mill kind's machining model, in machine seconds."""

    def cut_times(self, setup: Path | None, programs: Sequence[Path]) -> list[tuple[float, int]]:
        """Each program's least cut time (from any state the mill can start it in: after
        its setup or after any of ``programs``) and its characters on the line."""
        ...


"""``progress(done, total, bytes_sent)`` while a program goes onto a robot."""


@runtime_checkable
class Robot(Protocol):
    """A robot that moves parts between places by running named programs."""

    name: str
    link: Link

    @property
    def running(self) -> bool:
        """A program runs (as the host knows it)."""
        ...

    @property
    def ready(self) -> bool:
        """Initialized and idle: takes a program now."""
        ...

    @property
    def cold(self) -> bool:
        """Not initialized (its programs are gone)."""
        ...

    def host_status(self) -> HostStatus: ...
    async def initialize(self) -> None: ...
    async def stop(self) -> None: ...
    async def reset_errors(self) -> None: ...
    def needs_initialize(self, error: DeviceError) -> bool:
        """Whether a rejection says the robot must be initialized before it runs again."""
        ...

    async def ensure_program(
        self, name: str, program: Any, progress: RecordsProgress | None = None
    ) -> int:
        """Get ``program`` onto the robot (unless it is there) and return where it is."""
        ...

    async def start(self, slot: int) -> None: ...
    async def wait_end(
        self,
        done_output: int,
        *,
        timeout: float,
        poll: float = 0.1,
        watch_every: float = 0.0,
        expected: float = 0.0,
    ) -> None:
        """Wait for the running program's end. ``expected``: seconds it cannot end sooner
        (the cell's figure for it): a robot that has to be asked may leave its end unasked
        until then, watching its status only."""
        ...

    async def machine_status(self) -> Health: ...
    async def close(self) -> None: ...


class MillReading(Protocol):
    """A mill's status as its family reads it."""

    @property
    def shown(self) -> str:
        """In the machine's words."""
        ...

    @property
    def kind_condition(self) -> Condition: ...
    @property
    def ready(self) -> bool:
        """The machine says it takes input now (a Dyna's CTS)."""
        ...

    @property
    def set_up(self) -> bool:
        """Initialized and idle (it may still wait for ready)."""
        ...

    @property
    def takes_work(self) -> bool:
        """Set up and ready: a program may start now."""
        ...

    @property
    def awaiting_operator(self) -> bool:
        """Its setup went out; the operator has yet to finish it."""
        ...

    @property
    def waiting_for(self) -> str | None:
        """What it waits for, in its words (None: nothing)."""
        ...


def setup_lost(reading: MillReading, *, running: bool) -> bool:
    """True if a mill's ``reading`` says it lost its setup: not set up, not waiting for its
    operator to finish one, doing nothing (not ready or idle, no alarm) and no run of the
    host's on it. What a machine power-cycled behind the host's back shows: a controller
    that believed it set up (``initialized``) sets it up again."""
    return (
        not running
        and not reading.set_up
        and not reading.awaiting_operator
        and reading.kind_condition in (Condition.NOT_READY, Condition.IDLE)
    )


@runtime_checkable
class Mill(Protocol):
    """A machine that cuts a part with a program, after a setup."""

    name: str
    link: Link

    @property
    def initialized(self) -> bool: ...
    @property
    def state_text(self) -> str:
        """Its host state in the machine's words."""
        ...

    @property
    def running(self) -> bool:
        """A program runs (as the host knows it)."""
        ...

    @property
    def manual(self) -> bool:
        """In its operator's hands: nothing of the host's runs there."""
        ...

    @property
    def ready_wait(self) -> float:
        """Seconds it may take to show ready."""
        ...

    @property
    def setup_timeout(self) -> float:
        """Seconds its operator may take to finish a setup."""
        ...

    def host_status(self) -> MillReading:
        """Its status from the host's state, no byte sent (while a step runs)."""
        ...

    async def setup(self, program: Path, *, force: bool) -> None: ...
    async def run(
        self, program: Path, *, progress: Callable[[RunProgress], None] | None = None
    ) -> None: ...
    async def status(self) -> MillReading: ...
    async def end(self) -> object:
        """Stop: back to the operator's hands."""
        ...

    async def close(self) -> None: ...


# -- holding a kind's driver to its family -------------------------------------------------------


class KindContractError(CellctlError):
    """A kind's driver does not keep its family's protocol (a member missing, a reading of
    the wrong type): the message names the machine, its kind and where the kind comes from."""


FAMILY_PROTOCOLS: dict[str, type] = {"robot": Robot, "mill": Mill}


def protocol_members(protocol: type) -> dict[str, str]:
    """A protocol's members, each as a message names it: ``status()`` for a method,
    ``shown`` for an attribute or a property."""
    members: dict[str, str] = {}
    for cls in reversed(protocol.__mro__):
        if cls in (object, Protocol) or cls.__module__ == "typing":
            continue
        for name in getattr(cls, "__annotations__", {}):
            members[name] = name
        for name, value in vars(cls).items():
            if not name.startswith("_"):
                members[name] = f"{name}()" if callable(value) else name
    return members


def missing_members(obj: object, protocol: type) -> list[str]:
    """The members of ``protocol`` that ``obj`` has not, as a message names them."""
    return [shown for name, shown in protocol_members(protocol).items() if not hasattr(obj, name)]


def checked_reading(reading: object, who: str, what: str) -> MillReading:
    """``reading`` (what ``what`` gave: ``"status()"``) as a :class:`MillReading` whose
    ``kind_condition`` is a :class:`Condition` (a condition's value, ``"idle"``, is taken
    for it); :class:`KindContractError` naming ``who`` otherwise."""
    missing = missing_members(reading, MillReading)
    if missing:
        raise KindContractError(
            f"{who}: its {what} gave a {type(reading).__name__}, not a reading "
            f"(no {', '.join(missing)})"
        )
    condition = reading.kind_condition  # type: ignore[attr-defined]
    if not isinstance(condition, Condition):
        try:
            condition = Condition(condition)
        except ValueError:
            known = ", ".join(c.value for c in Condition)
            raise KindContractError(
                f"{who}: its {what} reading's kind_condition is {condition!r}, "
                f"not a condition ({known})"
            ) from None
        return _Coerced(reading, condition)
    return reading  # type: ignore[return-value]


@dataclass(frozen=True)
class _Coerced:
    """A reading whose condition was given as its value (``"idle"``): the same reading,
    its condition the :class:`Condition`."""

    reading: Any
    kind_condition: Condition

    def __getattr__(self, name: str) -> Any:
        return getattr(self.reading, name)

    def __str__(self) -> str:
        return str(self.reading)


def checked_driver(driver: Any, family: str, who: str) -> None:
    """Refuse ``driver`` (:class:`KindContractError` naming ``who``) unless it has every
    member of ``family``'s protocol; a mill's readings (``status()``, ``host_status()``)
    are then checked as they come (:func:`checked_reading`)."""
    protocol = FAMILY_PROTOCOLS[family]
    missing = missing_members(driver, protocol)
    if missing:
        raise KindContractError(f"{who}: its driver has no {', '.join(missing)}")
    if family != "mill":
        return
    status = driver.status
    host_status = driver.host_status

    async def checked_status() -> MillReading:
        return checked_reading(await status(), who, "status()")

    def checked_host_status() -> MillReading:
        return checked_reading(host_status(), who, "host_status()")

    try:  # on the instance: the driver stays itself (its class, its menu's isinstance)
        setattr(driver, "status", checked_status)  # noqa: B010
        setattr(driver, "host_status", checked_host_status)  # noqa: B010
    except (AttributeError, TypeError):
        pass  # slots, a frozen driver: its readings go unchecked
