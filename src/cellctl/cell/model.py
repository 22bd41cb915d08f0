"""What the controller knows and is told: each machine's view, its events, its options.

Part of M, the world model (spec ``cell.md``): :class:`MachineView` per machine (state, step,
service, failures, progress), :class:`Event` lines of the log, :class:`ControllerOptions`
from ``[cell]`` in cell.toml, and the mailbox wrapper that tells the controller's listeners
of every order change and report.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cellctl.cell.config import CellConfig
from cellctl.cell.orders import OrderBox
from cellctl.cell.scheduler import DOWNSTREAM_FIRST, ONE_AT_A_TIME, check_policy
from cellctl.kinds import Condition, LastError
from cellctl.kinds.families import RunProgress

#: Robot output a cell program raises when its cycle is done (the example cell's wiring).
DEFAULT_DONE_OUTPUT = 6


@dataclass
class MachineView:
    """What the controller knows of one machine, for the live view and the summary."""

    name: str
    kind: str
    state: str = "not connected"
    """The machine's state in its own words ("Executing", "Initialized, EXECUTING")."""
    step: str = ""
    in_service: bool = True
    machine_condition: Condition = Condition.OFFLINE
    """What the machine itself is doing; :attr:`condition` adds the controller's view."""
    error: LastError | None = None
    failures: int = 0
    busy_s: float = 0.0
    progress: dict[str, Any] | None = None
    """A download or cut in progress: ``done``/``total`` and what they count, ``phase``."""

    @property
    def condition(self) -> Condition:
        """The condition every surface shows: out of service wins over what the machine
        says, and a machine idle between two looks while a step runs on it is busy."""
        if not self.in_service:
            return Condition.OUT_OF_SERVICE
        if self.step and self.machine_condition is Condition.IDLE:
            return Condition.BUSY
        return self.machine_condition

    def show(self, state: str, condition: Condition, error: LastError | None = None) -> None:
        """Set what the machine says: its state's words and their condition. ``error`` is kept
        while the machine is offline or in alarm, and forgotten once it is seen well again."""
        self.state = state
        self.machine_condition = condition
        if condition in (Condition.OFFLINE, Condition.ALARM):
            self.error = error or self.error
        else:
            self.error = None

    def report_progress(self, done: int, total: int, unit: str, phase: str, **more: Any) -> bool:
        """Note progress (``more``: e.g. the program, block n of m); True when it moved by a
        percent or changed phase (worth telling)."""
        old = self.progress
        self.progress = {"done": done, "total": total, "unit": unit, "phase": phase, **more}
        if old is None or old["phase"] != phase or old["unit"] != unit:
            return True
        return int(100 * done / max(total, 1)) != int(100 * old["done"] / max(old["total"], 1))

    def report_run(self, p: RunProgress, program: str | None, since: float) -> bool:
        """:meth:`report_progress` of a mill's run (``program`` begun at ``since``): bytes,
        block n of m, phase and the run's estimate, for the controller's cuts and the hand's."""
        return self.report_progress(
            p.bytes_sent,
            p.bytes_total,
            "bytes",
            p.phase,
            program=program,
            block=p.block,
            blocks=p.blocks,
            since=since,
            estimate_s=p.estimate_s,
            estimate_done_s=p.estimate_done_s,
            estimate_cap_s=p.estimate_cap_s,
            at=p.at,
            running=p.running,
        )


@dataclass
class Event:
    """One line of the controller's log (also posted as a report where it matters)."""

    time: float
    text: str


@dataclass
class ControllerOptions:
    """Knobs of the controller, from ``[cell]`` in cell.toml."""

    poll_period: float = 0.5
    retries: int = 2
    fail_limit: int = 3
    done_output: int = DEFAULT_DONE_OUTPUT
    transfer_timeout: float = 120.0
    interlock_timeout: float = 30.0
    pallet_timeout: float = 60.0
    read_limit: float = 0.0
    """0: half the poll period (a silent machine is then told within one period)."""
    door_start_timeout: float = 0.0
    """0: half the poll period. A commanded door still at its end position then is stuck."""
    one_at_a_time: bool = False
    policy: str = DOWNSTREAM_FIRST
    """Which waiting part the robot loads next (:data:`cellctl.cell.scheduler.POLICIES`);
    ``one_at_a_time=True`` is the policy ``one-at-a-time``."""
    durable: bool = True
    """False only for a throwaway copy of a cell (a plan's): the machines' state files are
    not synced to disk at each change, as its journal and mailbox are not."""

    def __post_init__(self) -> None:
        check_policy(self.policy)
        if self.one_at_a_time:
            self.policy = ONE_AT_A_TIME
        self.one_at_a_time = self.policy == ONE_AT_A_TIME
        if self.read_limit <= 0:
            self.read_limit = self.poll_period / 2
        if self.door_start_timeout <= 0:
            self.door_start_timeout = self.poll_period / 2

    @classmethod
    def from_config(cls, config: CellConfig, **overrides: Any) -> ControllerOptions:
        cell = config.raw.get("cell", {})
        values: dict[str, Any] = {"poll_period": config.poll_period}
        for key in ("retries", "fail_limit", "done_output", "transfer_timeout"):
            if key in cell:
                values[key] = cell[key]
        for key in ("interlock_timeout", "pallet_timeout", "read_limit", "door_start_timeout"):
            if key in cell:
                values[key] = float(cell[key])
        values.update(overrides)
        return cls(**values)


#: Chunks of traffic the controller keeps in memory (all machines), for the API's tail.
TRAFFIC_KEPT = 4000


class NotifyingMailbox:
    """The mailbox, telling the controller's listeners of every order change and report."""

    def __init__(self, mailbox: OrderBox, touch: Callable[[], None]) -> None:
        self._mailbox = mailbox
        self._touch = touch

    def __getattr__(self, name: str) -> Any:
        return getattr(self._mailbox, name)

    def set_order_state(self, order_id: str, state: str, note: str = "") -> Any:
        result = self._mailbox.set_order_state(order_id, state, note)
        self._touch()
        return result

    def post_report(self, kind: str, text: str, **fields: Any) -> Any:
        result = self._mailbox.post_report(kind, text, **fields)
        self._touch()
        return result
