"""``plan.run``: a plan of the running cell, played on a copy of it::

    answer = await dispatcher.call("plan.run", {"shift": "8h", "fault": ["cnc2:down@10:00-11:00"]})
    answer["plan"]["plans"][0]["orders"]      # per order: finishes when, due, verdict
    answer["svg"]                             # the Gantt chart

The snapshot is the cell's state now (:mod:`cellctl.plan.snapshot`): its open orders with
what remains of them, the parts held, the machines out of service. The plan is played by the
engine on its own virtual-time loop in a worker thread, on a copy of the cell's
configuration: the controller's loop goes on (it waits for nothing of the plan's), and
nothing of the running cell is written. One plan at a time per service: a second call while
one plays is refused, not queued (a plan may take seconds of the computer's time).

Role: **viewer**. A plan acts on nothing: it reads what ``cell.status`` shows and plays it on a
copy, so a planner or an instructor who may not act on the cell may ask "what if". What it
costs (the computer's time) is bounded: one plan at a time, at most 31 days ahead.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.service.access import CellAccess
from cellctl.service.functions import Progress

#: The most ``add`` and ``fault`` entries one call may hold.
MAX_ENTRIES = 20
_Entry = Annotated[str, Field(min_length=1, max_length=200)]


class PlanParams(BaseModel):
    """``plan.run``'s parameters: the CLI's options, as it types them."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    shift: str | None = Field(default=None, min_length=1, max_length=40)
    until: str | None = Field(default=None, min_length=1, max_length=60)
    add: list[_Entry] = Field(default_factory=list, max_length=MAX_ENTRIES)
    fault: list[_Entry] = Field(default_factory=list, max_length=MAX_ENTRIES)
    policy: str = Field(default="default", min_length=1, max_length=200)
    seed: int = Field(default=0, ge=0, le=2**63 - 1)


_playing = threading.Lock()


async def plan_run(access: CellAccess, p: PlanParams, progress: Progress | None) -> Any:
    """Snapshot the cell, then check the inputs and play them in a worker thread; answer the
    plan (its figures, inputs and chart)."""
    from cellctl.plan.run import play_in_temp
    from cellctl.plan.snapshot import open_work, out_of_service
    from cellctl.plan.spec import plan_inputs

    if not _playing.acquire(blocking=False):
        raise UsageError("a plan is being played already: ask again when it has ended")
    try:
        # The snapshot on the loop (the journal and mailbox are this thread's); reading the
        # configuration (programs compiled) and the play in the worker.
        journal = access.journal()
        orders, held = open_work(access.mailbox(), journal)
        stopped = out_of_service(journal)
        start = current_clock().now()

        def plan() -> Any:
            inputs, policies = plan_inputs(
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
            )
            return play_in_temp(inputs, policies)

        result = await asyncio.to_thread(plan)
    finally:
        _playing.release()
    return {"plan": result.as_dict(), "svg": result.svg}
