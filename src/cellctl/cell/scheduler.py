"""Task decomposition and scheduling (H): what the robot does next, decided from the world.

A part of type T follows ``conveyor → mill₁ → … → millₖ → conveyor``: k machining tasks and
k+1 transfers (robot programs ``conveyor_to_cnc1``, ``cnc1_to_cnc2``, ``cnc2_to_conveyor``).
The mills cut in parallel; the one robot serves whichever needs it. Each time the robot is
free, :func:`next_transfer` picks, in this order:

1. **unload**: a part finished at the last mill of its route goes to the conveyor;
2. **advance**: a part finished at a mill goes on to its next mill, if that mill is empty;
3. **load**: the next waiting part (highest order priority, then oldest) goes from the
   conveyor to its first mill, if that mill is empty and a pallet stands at the pick-up.

Downstream first: moving a finished part on frees the mill behind it, so the line never
blocks itself (a mill holding a finished part it cannot pass on would stop the line) and
every mill gets its next part as early as the robot can bring it. A mill that holds a part
needing the operator (held) or that is out of service takes no part.

Mill programs go to the mill with DOWNLOAD (program execute mode) for every part. Loading a
program once and starting it per part with GO (through the PLC output) would save only the
program's transfer time, and needs the mill's panel set to PROGRAM LOAD by its operator,
which the host cannot do. For the example cell's programs (about 1,000 characters, 2.3 s at
4800 7E2, against 12-14 minutes of cutting) that is under 0.3 % of a cut, so this policy does
not use GO; a cell whose mills sit in PROGRAM LOAD mode would need it (see the mill driver's
``load`` and ``go``).

Policies (:data:`POLICIES`, ``ControllerOptions(policy=...)``, ``cellctl plan --policy``) change
only which waiting part is loaded next:

- ``downstream-first`` (the default): as above, highest order priority, then oldest;
- ``one-at-a-time``: the source's way of working, for comparison: one part goes through its
  whole route before the next is loaded (``one_at_a_time=True`` says the same);
- ``shortest-first``: among the parts of the highest priority, the part type with the least
  machining (shortest processing time, from ``work_s``: seconds of machining per part type),
  then oldest. It finishes more parts early in a shift; a long part type waits.

The lower bound the benchmark measures a makespan against (:func:`lower_bound`) is the
bottleneck bound: no resource can finish before it has done all its work, so

    makespan >= max( robot: sum of all transfer durations,
                     each mill M: head(M) + sum over parts of (load transfer into M +
                              machining on M + unload transfer out of M) + tail(M) )

where head(M) is the least time before the first part can reach M (the transfers and
machining before M on the shortest route through it) and tail(M) the least time after the
last part leaves M. A mill is occupied while the robot loads and unloads it, so those
transfers count for it too. The durations are given: :mod:`cellctl.cell.physics` gives what
the machines physically take (the physical bound, which no controller can beat); the means a
run measured give how busy the bottleneck was in that run (a sum over the batch's parts of
means is exactly the measured total; given the least measured durations too, head and tail use
them, so that bound holds for the very run measured).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from cellctl.cell.config import CONVEYOR, PartType, transfer_name
from cellctl.errors import UsageError

DOWNSTREAM_FIRST = "downstream-first"
ONE_AT_A_TIME = "one-at-a-time"
SHORTEST_FIRST = "shortest-first"
#: The scheduler's policies (see the module docstring).
POLICIES = (DOWNSTREAM_FIRST, ONE_AT_A_TIME, SHORTEST_FIRST)


def check_policy(policy: str) -> str:
    """``policy`` if it is one of :data:`POLICIES`; :class:`UsageError` otherwise."""
    if policy not in POLICIES:
        raise UsageError(f"no scheduler policy {policy!r}; known: {', '.join(POLICIES)}")
    return policy


@dataclass(frozen=True)
class PartState:
    """What the scheduler needs to know of a part."""

    id: str
    part_type: str
    location: str
    route_index: int  # machining steps done
    status: str  # waiting, active, held, done, scrapped
    priority: int = 0
    order_seq: int = 0  # order of arrival; lower first


@dataclass(frozen=True)
class Transfer:
    """A robot task: move ``part_id`` from ``source`` to ``target`` with ``program``."""

    part_id: str
    source: str
    target: str

    @property
    def program(self) -> str:
        return transfer_name(self.source, self.target)


def next_stop(part: PartState, types: Mapping[str, PartType]) -> str:
    """Where the part goes after its current place: a mill, or the conveyor when done."""
    route = types[part.part_type].route
    return route[part.route_index].mill if part.route_index < len(route) else CONVEYOR


def ready_to_leave(part: PartState, types: Mapping[str, PartType]) -> bool:
    """True when the part sits at a mill and has been machined there."""
    route = types[part.part_type].route
    if part.location == CONVEYOR or part.status != "waiting":
        return False
    done_mills = [s.mill for s in route[: part.route_index]]
    return part.location in done_mills


def next_transfer(
    parts: Sequence[PartState],
    types: Mapping[str, PartType],
    *,
    mills_in_service: set[str],
    pallet_present: bool,
    outfeed_clear: bool = True,
    one_at_a_time: bool = False,
    policy: str = DOWNSTREAM_FIRST,
    work_s: Mapping[str, float] | None = None,
) -> Transfer | None:
    """The robot's next task, or None if nothing can move now (see the module docstring).

    ``policy`` one of :data:`POLICIES`; ``work_s`` (part type -> seconds of machining) is
    what ``shortest-first`` ranks by (a part type missing from it counts as longest)."""
    one_at_a_time = one_at_a_time or policy == ONE_AT_A_TIME
    occupied = {p.location for p in parts if p.location != CONVEYOR and p.status != "done"}
    at_mills = [p for p in parts if p.location != CONVEYOR and p.status in ("waiting", "active")]
    leaving = [p for p in parts if ready_to_leave(p, types)]
    # 1. unload finished parts
    if outfeed_clear:
        for p in leaving:
            if next_stop(p, types) == CONVEYOR:
                return Transfer(p.id, p.location, CONVEYOR)
    # 2. advance parts to their next mill
    for p in leaving:
        target = next_stop(p, types)
        if target != CONVEYOR and target not in occupied and target in mills_in_service:
            return Transfer(p.id, p.location, target)
    # 3. load the next waiting part
    if not pallet_present:
        return None
    if one_at_a_time and (at_mills or any(p.status == "held" for p in parts)):
        return None
    if policy == SHORTEST_FIRST:
        work = work_s or {}

        def key(p: PartState) -> tuple[float, ...]:
            return (-p.priority, work.get(p.part_type, float("inf")), p.order_seq)
    else:

        def key(p: PartState) -> tuple[float, ...]:
            return (-p.priority, p.order_seq)

    for p in sorted(waiting_at_conveyor(parts), key=key):
        first = next_stop(p, types)
        if first not in occupied and first in mills_in_service:
            return Transfer(p.id, CONVEYOR, first)
    return None


def waiting_at_conveyor(parts: Sequence[PartState]) -> list[PartState]:
    """Parts not yet started (route index 0, waiting at the conveyor)."""
    return [
        p for p in parts if p.location == CONVEYOR and p.status == "waiting" and p.route_index == 0
    ]


def lower_bound(
    parts: Sequence[str],
    types: Mapping[str, PartType],
    transfer_s: Mapping[str, float],
    machining_s: Mapping[tuple[str, str], float],
    *,
    least_transfer_s: Mapping[str, float] | None = None,
    least_machining_s: Mapping[tuple[str, str], float] | None = None,
) -> float:
    """The bottleneck bound of the module docstring for ``parts`` (a list of part types).

    ``transfer_s[program]`` is a transfer's duration, ``machining_s[(mill, program)]`` a
    machining step's duration (both measured means); ``least_*``, if given, the least
    measured durations, used for head and tail.
    """
    terms = resource_bounds(
        parts,
        types,
        transfer_s,
        machining_s,
        least_transfer_s=least_transfer_s,
        least_machining_s=least_machining_s,
    )
    return max(terms.values())


def resource_bounds(
    parts: Sequence[str],
    types: Mapping[str, PartType],
    transfer_s: Mapping[str, float],
    machining_s: Mapping[tuple[str, str], float],
    *,
    least_transfer_s: Mapping[str, float] | None = None,
    least_machining_s: Mapping[tuple[str, str], float] | None = None,
) -> dict[str, float]:
    """Each resource's term of :func:`lower_bound`: ``{"robot": ..., mill: ...}``."""
    least_t = least_transfer_s or transfer_s
    least_m = least_machining_s or machining_s
    robot = 0.0
    mill_work: dict[str, float] = {}
    head: dict[str, float] = {}
    tail: dict[str, float] = {}
    for name in parts:
        route = types[name].route
        legs = [transfer_s[t] for t in types[name].transfers()]
        cuts = [machining_s[(s.mill, s.name)] for s in route]
        least_legs = [least_t[t] for t in types[name].transfers()]
        least_cuts = [least_m[(s.mill, s.name)] for s in route]
        robot += sum(legs)
        for i, step in enumerate(route):
            mill_work[step.mill] = mill_work.get(step.mill, 0.0) + legs[i] + cuts[i] + legs[i + 1]
            before = sum(least_legs[:i]) + sum(least_cuts[:i])
            after = sum(least_legs[i + 2 :]) + sum(least_cuts[i + 1 :])
            head[step.mill] = min(head.get(step.mill, before), before)
            tail[step.mill] = min(tail.get(step.mill, after), after)
    bounds = {"robot": robot}
    bounds.update({m: head[m] + w + tail[m] for m, w in mill_work.items()})
    return bounds
