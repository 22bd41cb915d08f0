"""The records of the cell's status: :class:`CellStatus` and its parts (the cell, each machine
with its step, progress and error, the orders, parts, alarms and events) and
:class:`StatusUpdate`, the difference between two statuses. Pydantic models, frozen, no unknown
keys: every surface (the API, the console, the dashboard, OPC UA) reads them by field.

Import them from :mod:`cellctl.service.status`, which re-exports them beside what makes,
compares and describes a status (``build_status``, ``difference``, ``apply_update``,
``status_schema``)::

    from cellctl.service.status import CellStatus, MachineStatus

    status.machines["cnc1"].condition                # Condition.BUSY: never a word search
    status.stable()                                  # without the figures of VOLATILE
"""

from __future__ import annotations

import enum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from cellctl.kinds import Condition
from cellctl.kinds.families import estimated_done

#: Events a status carries.
STATUS_EVENTS = 30


class Model(BaseModel):
    """Base of the status' objects: no unknown keys, never changed once built."""

    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)


class CellMode(enum.StrEnum):
    """What the cell as a whole is doing."""

    RUNNING = "running"
    """The controller dispatches work."""
    PAUSED = "paused"
    """Paused by the operator: steps in flight finish, no new step starts."""
    STOPPING = "stopping"
    """The controller is shutting down."""
    EMERGENCY_STOP = "emergency-stop"
    """An emergency stop (the PLC's input, or the operator's) is active."""
    NO_CONTROLLER = "no-controller"
    """No controller runs: the machines are driven by hand (standalone)."""


class StepKind(enum.StrEnum):
    """What kind of step runs on a machine."""

    TRANSFER = "transfer"
    """A robot program moving a part between two places."""
    MACHINE = "machine"
    """A mill cutting a part (a route step)."""
    MANUAL = "manual"
    """A manual function the operator runs."""


class CellInfo(Model):
    name: str = Field(description="The cell's name (cell.toml, else its directory's).")
    directory: str = Field(description="The cell directory.")
    access: Literal["attached", "standalone"] = Field(
        description="attached: a controller runs the cell; standalone: this process drives "
        "the machines by hand."
    )
    mode: CellMode = Field(description="What the cell is doing.")
    paused: bool = Field(description="Paused by the operator (or by an emergency stop).")
    started_at: float = Field(description="When the controller (or this process) started, s.")
    pid: int = Field(description="The serving process.")
    time: float = Field(description="When this status was built, s since the epoch.")


class StepInfo(Model):
    what: StepKind = Field(description="transfer, machine or manual.")
    program: str | None = Field(
        default=None, description="The robot program or the route step's name."
    )
    part_id: str | None = Field(default=None, description="The part the step works on.")
    started: float | None = Field(default=None, description="When the step began, s.")


class ProgressInfo(Model):
    phase: str = Field(description="downloading, waiting, sending, machining ...")
    done: int = Field(description="How much is done, in unit.")
    total: int = Field(description="How much there is, in unit.")
    unit: str = Field(description="bytes (a mill's program) or records (a robot's).")
    fraction: float = Field(
        description="How far the run is, 0 to 1: of its estimate when it has one (the line's "
        "time and the program's own cut time, corrected by the machine's reports), else "
        "done / total."
    )
    program: str | None = Field(default=None, description="The program being sent.")
    block: int | None = Field(default=None, description="The block being sent (a mill).")
    blocks: int | None = Field(default=None, description="Blocks of the program (a mill).")
    since: float | None = Field(default=None, description="When the step began, s.")
    rate_per_s: float | None = Field(default=None, description="unit per second so far.")
    time_left_s: float | None = Field(
        default=None,
        description="Seconds left: from the run's estimate (see fraction), else from the "
        "rate, else from the program's own estimate and the step's start.",
    )
    estimate_s: float | None = Field(
        default=None,
        description="The whole run's estimated seconds (line and cut), as the machine runs.",
    )
    estimate_done_s: float | None = Field(
        default=None,
        description="Of estimate_s, done at estimate_at (the machine's last report).",
    )
    estimate_cap_s: float | None = Field(
        default=None,
        description="The most estimate_done_s grows to before the machine reports again (the "
        "end of the block it works on).",
    )
    estimate_at: float | None = Field(default=None, description="When it was reported, s.")
    running: bool = Field(
        default=False,
        description="The machine works on: done grows with the clock from estimate_at, up "
        "to estimate_cap_s (a client may draw it so between updates).",
    )
    stall_s: float | None = Field(
        default=None,
        description="Seconds the machine has waited for data this run, its axes stopped (a "
        "drip-feed), where it is known.",
    )

    def estimated(self, now: float) -> tuple[float, float | None]:
        """``(fraction, time left)`` at ``now``: a client's live figures between updates."""
        raw = {
            "estimate_s": self.estimate_s,
            "estimate_done_s": self.estimate_done_s,
            "estimate_cap_s": self.estimate_cap_s,
            "at": self.estimate_at,
            "running": self.running,
        }
        done = estimated_done(raw, now)
        if done is None or not self.estimate_s:
            return self.fraction, self.time_left_s
        return done / self.estimate_s, self.estimate_s - done


class ErrorInfo(Model):
    code: int | None = Field(default=None, description="The machine's or the source's code.")
    text: str = Field(description="What went wrong, in the user's words.")


class MachineStatus(Model):
    name: str = Field(description="The machine's name in cell.toml.")
    kind: str = Field(description="Its kind (cell.toml's kind).")
    family: str = Field(description="robot, mill or plc: where cell.toml puts it.")
    condition: Condition = Field(description="What it is doing, for every surface.")
    state: str = Field(description="Its state in the machine's own words (shown, not parsed).")
    step: StepInfo | None = Field(default=None, description="The step in flight on it.")
    part: str | None = Field(default=None, description="The part it works on or holds.")
    progress: ProgressInfo | None = Field(default=None, description="A download or cut.")
    error: ErrorInfo | None = Field(default=None, description="Its last error.")
    failures: int = Field(description="Failed steps in a row.")
    busy_s: float = Field(
        description="Seconds spent in steps since the start, the step in flight included."
    )
    utilization: float = Field(description="busy_s over the time since the start, 0 to 1.")
    in_service: bool = Field(description="In automatic service.")
    out_reason: str = Field(description="Why it is out of service ('' when in).")
    manual: bool = Field(description="A manual function may drive it now.")

    def stable(self) -> MachineStatus:
        """This machine without the figures that move with the clock alone (:data:`VOLATILE`)."""
        progress = self.progress
        if progress is not None:
            progress = progress.model_copy(
                update={"rate_per_s": None, "time_left_s": None, "fraction": 0.0}
            )
        return self.model_copy(update={"busy_s": 0.0, "utilization": 0.0, "progress": progress})


class OrderInfo(Model):
    id: str = Field(description="The order's id.")
    part_type: str = Field(description="What to make (a part type of cell.toml).")
    qty: int = Field(description="How many.")
    priority: int = Field(description="Higher first.")
    state: str = Field(description="posted, accepted, in-progress, held, done, ...")
    created: float = Field(description="When it was posted, s.")
    updated: float = Field(description="When its state last changed, s.")
    note: str = Field(default="", description="Why it is in its state.")
    parts: dict[str, int] = Field(description="Its parts counted by status.")
    blocked: str = Field(
        default="",
        description="Why it cannot go on: its parts need a machine out of service, which and "
        "why (also at the start of note); '' when it can.",
    )
    # Both with defaults: a status from a cellctl before due times has neither.
    due: float | None = Field(
        default=None, description="When it is due, s (orders.submit's due; null: no due time)."
    )
    late: bool = Field(
        default=False,
        description="Done after its due time, or not done (open, or failed) and past it on the "
        "cell's clock (orders.list's late); false without a due time, or cancelled.",
    )


class PartInfo(Model):
    id: str = Field(description="The part's id: its order's, then -N.")
    order_id: str = Field(description="Its order.")
    part_type: str = Field(description="Its part type.")
    seq_in_order: int = Field(description="N: its number in its order, from 1.")
    route_index: int = Field(description="Route operations done.")
    location: str = Field(description="conveyor, a machine's name, or out.")
    status: str = Field(description="waiting, active or held.")
    updated: float = Field(description="When it last changed, s.")
    note: str = Field(default="", description="Why it is held.")
    may_be_in: list[str] = Field(
        default_factory=list,
        description="A held part: the machines it may physically be in (parts.scrap needs "
        "taken_out then).",
    )


class AlarmInfo(Model):
    id: int = Field(description="The alarm's number (alarms.clear takes it).")
    raised: float = Field(description="When it was raised, s.")
    machine: str = Field(description="The machine it is about (cell, plc, a machine's name).")
    code: str = Field(description="What kind of fault (link, status, estop, ...).")
    text: str = Field(description="What happened, in the user's words.")
    state: str = Field(description="active (the status lists active alarms only).")
    cleared: float | None = Field(default=None, description="When it was cleared, s.")
    cleared_by: str = Field(default="", description="Who cleared it.")
    priority: str = Field(default="medium", description="high, medium or low (from its code).")
    acked: float | None = Field(
        default=None, description="When it was acknowledged, s (null: unacknowledged)."
    )
    acked_by: str = Field(default="", description="Who acknowledged it.")
    returned: float | None = Field(
        default=None,
        description="When its condition went away (returned to normal), s; null: still seen.",
    )
    shelved_until: float | None = Field(
        default=None, description="Shelved (not shown as unacknowledged) until then, s."
    )


class EventInfo(Model):
    time: float = Field(description="When, s since the epoch.")
    text: str = Field(description="What happened.")


class CellStatus(Model):
    """The cell's status (``cell.status``, ``GET /api/status``)."""

    cell: CellInfo = Field(description="The cell as a whole.")
    machines: dict[str, MachineStatus] = Field(description="Every machine by name.")
    orders: list[OrderInfo] = Field(description="Open orders and the latest others.")
    parts: list[PartInfo] = Field(description="Parts waiting, active or held.")
    alarms: list[AlarmInfo] = Field(description="Active alarms, oldest first.")
    events: list[EventInfo] = Field(description=f"The last {STATUS_EVENTS} events.")

    def stable(self) -> CellStatus:
        """This status without the figures that move with the clock alone (:data:`VOLATILE`)."""
        return self.model_copy(
            update={
                "cell": self.cell.model_copy(update={"time": 0.0}),
                "machines": {n: m.stable() for n, m in self.machines.items()},
            }
        )

    def held(self) -> list[PartInfo]:
        """The held parts."""
        return [p for p in self.parts if p.status == "held"]


class StatusUpdate(Model):
    """What changed between two statuses (``notify_status_update``; the module docstring)."""

    time: float = Field(description="When the newer status was built, s.")
    cell: CellInfo | None = Field(default=None, description="The cell, when it changed.")
    machines: dict[str, MachineStatus] | None = Field(
        default=None, description="The machines that changed or are new, whole, by name."
    )
    machines_gone: list[str] | None = Field(
        default=None, description="Machines no longer in the status."
    )
    orders: list[OrderInfo] | None = Field(default=None, description="All, when they changed.")
    parts: list[PartInfo] | None = Field(default=None, description="All, when they changed.")
    alarms: list[AlarmInfo] | None = Field(default=None, description="All, when they changed.")
    events: list[EventInfo] | None = Field(default=None, description="The new events only.")

    def empty(self) -> bool:
        return not self.model_fields_set - {"time"}

    def as_json(self) -> dict[str, Any]:
        """The JSON a subscriber is pushed: ``time`` and the keys that changed."""
        sent = self.model_fields_set | {"time"}
        return {k: v for k, v in self.model_dump(mode="json").items() if k in sent}


#: Figures that move with the clock alone: they make no update of their own.
VOLATILE = (
    "cell.time",
    "machines.*.busy_s",
    "machines.*.utilization",
    "progress.rate_per_s",
    "progress.time_left_s",
    "progress.fraction",
)
