"""``plan.run``: a plan of the running cell, played on a copy of it::

    answer = await dispatcher.call("plan.run", {"shift": "8h", "fault": ["cnc2:down@10:00-11:00"]})
    answer["plan"]["plans"][0]["orders"]      # per order: finishes when, due, verdict
    answer["svg"]                             # the Gantt chart

The snapshot is the cell's state now (:mod:`cellctl.plan.snapshot`): its open orders with
what remains of them and their due times (``cellctl submit --due``: the plan says on time or
late per order, as a plan of an orders file does), the parts held, the machines out of
service. The plan is played by the engine on its own virtual-time loop in a worker process
at a lower priority (:mod:`cellctl.service.offload`), on a copy of the cell's configuration:
the controller's loop goes on undisturbed (it waits for nothing of the plan's, and shares no
interpreter with it), and nothing of the running cell is written. A call cancelled (its
client gone) ends its play. One plan at a time per service: a second call while one plays is
refused, not queued (a plan may take seconds of the computer's time).

Role: **viewer**. A plan acts on nothing: it reads what ``cell.status`` shows and plays it on a
copy, so a planner or an instructor who may not act on the cell may ask "what if". What it
costs (the computer's time) is bounded: one plan at a time, at most 31 days ahead.

:func:`own_plan` is the same snapshot played for the factory (``[mailbox] plan_period``): the
cell's open work alone, and when it finishes, which the cell publishes in its retained state
(:class:`~cellctl.mailbox.mqtt.MqttBridge` plans one at a time, on a period and when its orders
or machines change).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import shutil
import tempfile
import threading
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from cellctl.cell.journal import Journal
from cellctl.cell.shift import time_scale_of
from cellctl.clock import current_clock
from cellctl.errors import MachineInUse, UsageError
from cellctl.files import read_text
from cellctl.kinds.menu import PrintableText
from cellctl.mailbox import Mailbox
from cellctl.plan.when import parse_poll
from cellctl.service.access import CellAccess
from cellctl.service.functions import Progress
from cellctl.service.offload import in_process

if TYPE_CHECKING:
    from cellctl.mailbox.mqtt import PlanEstimate
    from cellctl.plan.engine import HeldPart, PlanInputs, PlanOrder

#: The most ``add`` and ``fault`` entries one call may hold.
MAX_ENTRIES = 20
_Entry = Annotated[PrintableText, Field(min_length=1, max_length=200)]


class PlanParams(BaseModel):
    """``plan.run``'s parameters: the CLI's options, as it types them."""

    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)
    shift: PrintableText | None = Field(default=None, min_length=1, max_length=40)
    until: PrintableText | None = Field(default=None, min_length=1, max_length=60)
    add: list[_Entry] = Field(default_factory=list, max_length=MAX_ENTRIES)
    fault: list[_Entry] = Field(default_factory=list, max_length=MAX_ENTRIES)
    policy: PrintableText = Field(default="default", min_length=1, max_length=200)
    seed: int = Field(default=0, ge=0, le=2**63 - 1)
    #: How often the planned controller looks at idle machines, s (the plan's PLAN_POLL_S
    #: when not given): refused in the words the console and ``cellctl plan --poll`` use.
    poll: float | None = None

    @field_validator("poll", mode="before")
    @classmethod
    def _poll(cls, value: Any) -> float | None:
        if value is None:
            return None
        try:
            return parse_poll(value)
        except UsageError as e:
            raise ValueError(str(e)) from None


_playing = threading.Lock()


async def plan_run(access: CellAccess, p: PlanParams, progress: Progress | None) -> Any:
    """Snapshot the cell, check the inputs (in a thread: the configuration is read, programs
    compiled), then play them in a worker process (:mod:`cellctl.service.offload`); answer
    the plan (its figures, inputs and chart). ``progress``: told how far the play has gone
    (``{"policy", "played_s", "span_s"}``, a few times a second at most)."""
    from cellctl.plan.snapshot import open_work, out_of_service
    from cellctl.plan.spec import plan_inputs

    if not _playing.acquire(blocking=False):
        raise MachineInUse("a plan is being played already: ask again when it has ended")
    try:
        # The snapshot here (the journal and mailbox are this loop's).
        start = current_clock().now()
        scale = _time_scale(access.directory)
        with access.work_to_plan() as (mailbox, journal):
            orders, held = open_work(mailbox, journal, now=start, time_scale=scale)
            orders = with_due_times(orders, mailbox)
            stopped = out_of_service(journal)

        def inputs() -> tuple[PlanInputs, tuple[str, ...]]:
            return plan_inputs(
                access.directory,
                start=start,
                shift=p.shift,
                until=p.until,
                orders=orders,
                adds=p.add,
                faults=p.fault,
                policy=p.policy,
                seed=p.seed,
                out_of_service=stopped,
                held=held,
                **({} if p.poll is None else {"poll_period": p.poll}),
            )

        # Refused here, before a process starts: the inputs' own words, at once.
        played, policies = await asyncio.to_thread(inputs)
        told = None if progress is None else _progress_to(progress, played)
        # The play's directory is this process's: a play ended midway leaves nothing behind.
        with tempfile.TemporaryDirectory(prefix="cellctl-plan-") as tmp:
            return await in_process(_play_plan, played, policies, tmp, progress=told)
    finally:
        _playing.release()


def with_due_times(orders: tuple[PlanOrder, ...], mailbox: Mailbox) -> tuple[PlanOrder, ...]:
    """``orders`` (a snapshot's open orders) each with its due time in ``mailbox``, if any."""
    due = mailbox.due_times()
    return tuple(dataclasses.replace(o, due=due.get(o.order_id, o.due)) for o in orders)


def _progress_to(progress: Progress, inputs: PlanInputs) -> Callable[[Any], None]:
    """What the play's worker reports (``(policy, played_s)``, in the reader's thread) as
    the API's progress (``{"policy", "played_s", "span_s"}``), handed to this loop."""
    loop = asyncio.get_running_loop()
    span = inputs.until - inputs.start

    def told(item: Any) -> None:
        policy, played = item
        data = {"policy": policy, "played_s": round(played, 3), "span_s": span}
        with contextlib.suppress(RuntimeError):  # the loop closed: nobody waits any more
            loop.call_soon_threadsafe(progress, data)

    return told


def _play_plan(
    inputs: PlanInputs,
    policies: tuple[str, ...],
    workdir: str,
    progress: Callable[[Any], None] | None = None,
) -> dict[str, Any]:
    """:func:`plan_run`'s play in ``workdir``, in its worker process: the answer; how far
    it has gone to ``progress`` (``(policy, played_s)``)."""
    from cellctl.plan.run import play

    tell = None if progress is None else (lambda policy, played: progress((policy, played)))
    result = play(inputs, policies, Path(workdir), progress=tell)
    return {"plan": result.as_dict(), "svg": result.svg}


#: Where a cell's plan of its own work is played (replaced by the next one).
OWN_PLAN_DIR = Path("state") / "own-plan"


async def own_plan(
    directory: Path, mailbox: Mailbox, journal: Journal, horizon: float
) -> PlanEstimate:
    """The cell's open work now (as ``plan.run`` takes it) played forward on virtual time in a
    worker process: when the last open order would be done, in the running cell's seconds
    (an emulated cell's plan, played at the real machines' speed, is divided by its time
    scale). Work not done within ``horizon`` (seconds of the real machines' time) counts as
    done at its end. Nothing open: 0 at once. Played in ``directory/state/own-plan/``."""
    from cellctl.mailbox.mqtt import PlanEstimate
    from cellctl.plan.snapshot import open_work, out_of_service

    start = current_clock().now()
    orders, held = open_work(mailbox, journal, now=start, time_scale=_time_scale(directory))
    stopped = out_of_service(journal)
    if not orders:
        return PlanEstimate(planned_at=start, finish_s=0.0)
    try:
        finish_s = await in_process(_play_own, directory, start, horizon, orders, held, stopped)
    finally:  # a play ended midway (the cell stopped) removes nothing itself
        shutil.rmtree(directory / OWN_PLAN_DIR, ignore_errors=True)
    return PlanEstimate(planned_at=start, finish_s=finish_s)


def _time_scale(directory: Path) -> float:
    """The cell's ``[cell] time_scale`` (its file read as is: checked when it was loaded)."""
    return time_scale_of(tomllib.loads(read_text(directory / "cell.toml")))


def _play_own(
    directory: Path,
    start: float,
    horizon: float,
    orders: tuple[PlanOrder, ...],
    held: tuple[HeldPart, ...],
    stopped: tuple[str, ...],
) -> float:
    """:func:`own_plan`'s play, in its worker process: the finish, s from ``start``."""
    from cellctl.plan import engine
    from cellctl.plan.inputs import copy_config
    from cellctl.plan.spec import plan_inputs

    scale = _time_scale(directory)
    inputs, _ = plan_inputs(
        directory,
        start=start,
        shift=f"{max(1, round(horizon))}s",
        orders=orders,
        out_of_service=stopped,
        held=held,
    )
    work = directory / OWN_PLAN_DIR
    shutil.rmtree(work, ignore_errors=True)
    try:
        real = copy_config(directory, work / "config")
        run = engine.simulate(dataclasses.replace(inputs, cell_dir=real), work / "play")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    done = [t for t in run.finished.values() if t is not None]
    ends = inputs.until if len(done) < len(run.finished) else max(done, default=start)
    return max(0.0, ends - start) / scale
