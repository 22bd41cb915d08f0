"""The plan engine: the real cell controller, its drivers and the emulators on virtual time.

A plan plays a cell forward: the same :class:`~cellctl.cell.controller.CellController` that
runs the real cell, with its drivers, talking byte for byte to the machines' emulators over
``mem://`` lines (the PLC over an in-process Modbus/TCP pair), on an event loop whose time
jumps to the next timer whenever everything waits (:func:`cellctl.clock.run_virtual`). Each
character still takes its line time, each cut its machining time: only the waiting is
skipped. ::

    from cellctl.plan.engine import FaultWindow, PlanInputs, PlanOrder, simulate

    inputs = PlanInputs(
        cell_dir=Path("cell"),                       # cell.toml, robot/, programs/
        orders=(PlanOrder("A", "wax-robot-base", 20, due=friday_6pm),),
        start=monday_6am, until=monday_6am + 8 * 3600,
        faults=(FaultWindow("cnc2", "down", start=t10, end=t11),),
    )
    run = simulate(inputs, workdir=Path("plan-out"))  # a journal and mailbox in plan-out/
    run.finished                                      # {"A": 1764260712.3} (None: not done)

Times are unix seconds of the plan's wall clock (``start`` is the plan's "now").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

#: The mailbox's default order priority (``Mailbox.post_order``).
DEFAULT_PRIORITY = 0

#: The scheduler's policies a plan can try (``PlanInputs.policy``).
POLICIES = ("default", "one-at-a-time")


@dataclass(frozen=True)
class PlanOrder:
    """An order to play: ``qty`` parts of ``part_type`` (a part type of the cell's cell.toml).

    ``due``: when it is due (unix seconds), if it has a due time; the plan only reports it.
    """

    order_id: str
    part_type: str
    qty: int
    priority: int = DEFAULT_PRIORITY
    due: float | None = None


@dataclass(frozen=True)
class FaultWindow:
    """A fault on one machine from ``start`` to ``end`` (unix seconds; None: to the end).

    ``fault="down"``: the machine is out of service over the window, as an operator takes it
    out and puts it back. Any other name is the machine's emulator fault switch (as
    ``cellctl emulate cell --fault MACHINE:NAME[=ARG]`` takes it, ``arg`` its argument),
    switched on at ``start`` and off at ``end``, after which the plan's operator resolves
    what the cell holds: clears the alarms and releases held parts where they physically are.
    """

    machine: str
    fault: str
    start: float
    end: float | None = None
    arg: str | None = None


@dataclass(frozen=True)
class HeldPart:
    """A part the running cell holds for the operator now: it stays where it is, held."""

    order_id: str
    part_type: str
    location: str
    route_index: int = 0


@dataclass(frozen=True)
class PlanInputs:
    """Everything a plan is played from (saved beside its output: a plan is reproducible).

    ``cell_dir``: a cell directory (cell.toml, robot/, programs/), copied, never written;
    ``start``/``until``: the plan's wall-clock window (unix seconds); ``policy``: one of
    :data:`POLICIES`; ``seed``: for anything random in the emulators; ``out_of_service``:
    machines out of service at ``start``; ``held``: parts held at ``start``.
    """

    cell_dir: Path
    orders: tuple[PlanOrder, ...]
    start: float
    until: float
    faults: tuple[FaultWindow, ...] = ()
    policy: str = "default"
    seed: int = 0
    out_of_service: tuple[str, ...] = ()
    held: tuple[HeldPart, ...] = ()


@dataclass
class PlanRun:
    """What :func:`simulate` played.

    ``journal_path``: the run's journal (the same schema as a real cell's: steps, parts,
    alarms, with their virtual wall times); ``ended``: the virtual wall time the run stopped
    (every order done, or ``until``); ``wall_s``: real seconds it took; ``finished``: each
    order's finish time (unix seconds), None if it did not finish by ``ended``.
    """

    inputs: PlanInputs
    workdir: Path
    journal_path: Path
    ended: float
    wall_s: float
    finished: dict[str, float | None] = field(default_factory=dict)
    mailbox_path: Path | None = None


def simulate(inputs: PlanInputs, workdir: Path) -> PlanRun:
    """Play ``inputs`` on virtual time in ``workdir`` (made if needed; its cell copy, journal
    and mailbox are written there) and return what happened.

    Synchronous: it runs its own virtual-time event loop (:func:`cellctl.clock.run_virtual`),
    so call it from a thread (``asyncio.to_thread``) inside a running loop. Raises
    :class:`~cellctl.errors.UsageError` for inputs the cell cannot take (an unknown part
    type, machine, fault or policy; ``until`` before ``start``) before anything runs.
    """
    raise NotImplementedError("the plan engine is being built")


__all__ = [
    "DEFAULT_PRIORITY",
    "POLICIES",
    "FaultWindow",
    "HeldPart",
    "PlanInputs",
    "PlanOrder",
    "PlanRun",
    "simulate",
]
