"""How long the cell's open work will take, from the durations its journal measured.

::

    durations = measured(journal)                          # means of finished steps
    scale = cell_time_scale(config)                        # cell.shift: [cell] time_scale
    per_part = part_bounds(config.parts, durations, time_scale=scale)  # {"wax-robot-base": 41.2}
    left = finish_estimate(config.parts, open_types, durations, time_scale=scale)

Both use the scheduler's bottleneck bound (:func:`cellctl.cell.scheduler.resource_bounds`):
``part_bounds`` is what one more part of a type adds to the busiest resource, and
``finish_estimate`` the bound of the parts still open. A step never measured yet counts
:data:`UNMEASURED_TRANSFER_S` for a transfer and the program's own estimate for a cut
(from its toolpath; :data:`UNMEASURED_MACHINING_S` when it has none); each finished step
replaces the guess with the cell's own figure.

Both are in the cell's own seconds (its clock's, as the journal measures steps): the guesses
are the machines' seconds, so they are divided by ``time_scale`` (the cell's ``[cell]
time_scale``: an emulated cell's machines run that many times faster than real ones, 1 for
a real cell) here, the one place guesses and measurements meet. Without it, a type an
emulated cell has measured would count ``time_scale`` times less than one it has not.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from cellctl.cell.config import PartType
from cellctl.cell.journal import Journal, Step
from cellctl.cell.scheduler import resource_bounds

#: Seconds of the machines' time a robot transfer or a cut counts for before the cell has
#: measured one.
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


def _complete(types: Mapping[str, PartType], d: Durations, time_scale: float) -> Durations:
    """``d`` (measured: the cell's own seconds) with a guess for every step of ``types`` it
    has not measured, in the same seconds: the machines' seconds over ``time_scale``."""
    full = Durations(dict(d.transfer_s), dict(d.machining_s))  # means only: the bound's terms
    for t in types.values():
        for name in t.transfers():
            full.transfer_s.setdefault(name, UNMEASURED_TRANSFER_S / time_scale)
        for step in t.route:
            guess = step.machining_s if step.machining_s > 0 else UNMEASURED_MACHINING_S
            full.machining_s.setdefault((step.mill, step.name), guess / time_scale)
    return full


def finish_estimate(
    types: Mapping[str, PartType], parts: Sequence[str], d: Durations, *, time_scale: float
) -> float:
    """The bottleneck bound of the open parts (their part types), in the cell's own seconds
    (``time_scale``: the cell's ``[cell] time_scale``, 1 for a real cell)."""
    if not parts:
        return 0.0
    full = _complete(types, d, time_scale)
    return max(resource_bounds(parts, types, full.transfer_s, full.machining_s).values())


def part_bounds(
    types: Mapping[str, PartType], d: Durations, *, time_scale: float
) -> dict[str, float]:
    """What one more part of each type adds to the busiest resource's work, in the cell's own
    seconds (``time_scale`` as :func:`finish_estimate`'s)."""
    full = _complete(types, d, time_scale)
    out = {}
    for name in types:
        one = resource_bounds([name], types, full.transfer_s, full.machining_s)
        two = resource_bounds([name, name], types, full.transfer_s, full.machining_s)
        out[name] = max(two[r] - one[r] for r in one)
    return out
