"""How long the cell's open work will take, from the durations its journal measured.

::

    durations = measured(journal)                          # means of finished steps
    per_part = part_bounds(config.parts, durations)        # {"wax-robot-base": 41.2, ...}
    left = finish_estimate(config.parts, open_types, durations)

Both use the scheduler's bottleneck bound (:func:`cellctl.cell.scheduler.resource_bounds`):
``part_bounds`` is what one more part of a type adds to the busiest resource, and
``finish_estimate`` the bound of the parts still open. A step never measured yet counts
:data:`UNMEASURED_TRANSFER_S` for a transfer and the program's own estimate for a cut
(from its toolpath; :data:`UNMEASURED_MACHINING_S` when it has none); each finished step
replaces the guess with the cell's own figure.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from cellctl.cell.config import PartType
from cellctl.cell.journal import Journal, Step
from cellctl.cell.scheduler import resource_bounds

#: Seconds a robot transfer or a cut counts for before the cell has measured one.
UNMEASURED_TRANSFER_S = 30.0
UNMEASURED_MACHINING_S = 600.0


@dataclass
class Durations:
    """Measured seconds: the mean and the least of each robot program and (mill, program)."""

    transfer_s: dict[str, float] = field(default_factory=dict)
    machining_s: dict[tuple[str, str], float] = field(default_factory=dict)
    least_transfer_s: dict[str, float] = field(default_factory=dict)
    least_machining_s: dict[tuple[str, str], float] = field(default_factory=dict)

    def filled(self, other: Durations) -> Durations:
        """These durations, with ``other``'s for every step not measured here."""
        return Durations(
            {**other.transfer_s, **self.transfer_s},
            {**other.machining_s, **self.machining_s},
            {**other.least_transfer_s, **self.least_transfer_s},
            {**other.least_machining_s, **self.least_machining_s},
        )


def measured_durations(steps: Iterable[Step]) -> Durations:
    """Durations of the finished steps given (a step runs from its start to its end entry)."""
    transfers: dict[str, list[float]] = defaultdict(list)
    cuts: dict[tuple[str, str], list[float]] = defaultdict(list)
    for s in steps:
        if s.state != "finished" or s.ended is None:
            continue
        if s.kind == "transfer":
            transfers[s.program].append(s.ended - s.started)
        else:
            cuts[(s.machine, s.program)].append(s.ended - s.started)
    return Durations(
        {k: sum(v) / len(v) for k, v in transfers.items()},
        {k: sum(v) / len(v) for k, v in cuts.items()},
        {k: min(v) for k, v in transfers.items()},
        {k: min(v) for k, v in cuts.items()},
    )


def measured(journal: Journal) -> Durations:
    """The durations of the journal's finished steps."""
    return measured_durations(journal.steps())


def _complete(types: Mapping[str, PartType], d: Durations) -> Durations:
    """``d`` with a guess for every step of ``types`` it has not measured."""
    full = Durations(dict(d.transfer_s), dict(d.machining_s))  # means only: the bound's terms
    for t in types.values():
        for name in t.transfers():
            full.transfer_s.setdefault(name, UNMEASURED_TRANSFER_S)
        for step in t.route:
            guess = step.machining_s if step.machining_s > 0 else UNMEASURED_MACHINING_S
            full.machining_s.setdefault((step.mill, step.name), guess)
    return full


def finish_estimate(types: Mapping[str, PartType], parts: Sequence[str], d: Durations) -> float:
    """The bottleneck bound, in seconds, of the open parts (their part types)."""
    if not parts:
        return 0.0
    full = _complete(types, d)
    return max(resource_bounds(parts, types, full.transfer_s, full.machining_s).values())


def part_bounds(types: Mapping[str, PartType], d: Durations) -> dict[str, float]:
    """What one more part of each type adds to the busiest resource's work, in seconds."""
    full = _complete(types, d)
    out = {}
    for name in types:
        one = resource_bounds([name], types, full.transfer_s, full.machining_s)
        two = resource_bounds([name, name], types, full.transfer_s, full.machining_s)
        out[name] = max(two[r] - one[r] for r in one)
    return out
