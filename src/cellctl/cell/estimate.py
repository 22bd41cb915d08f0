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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from cellctl.cell.config import PartType
from cellctl.cell.journal import Journal
from cellctl.cell.scheduler import resource_bounds

#: Seconds a robot transfer or a cut counts for before the cell has measured one.
UNMEASURED_TRANSFER_S = 30.0
UNMEASURED_MACHINING_S = 600.0


@dataclass
class Durations:
    """Mean measured seconds per robot program and per (mill, program)."""

    transfer_s: dict[str, float] = field(default_factory=dict)
    machining_s: dict[tuple[str, str], float] = field(default_factory=dict)


def measured(journal: Journal) -> Durations:
    """The means of the journal's finished steps."""
    sums: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    for s in journal.steps():
        if s.state == "finished" and s.ended is not None:
            sums[(s.kind, s.machine, s.program)].append(s.ended - s.started)
    out = Durations()
    for (kind, machine, program), values in sums.items():
        mean = sum(values) / len(values)
        if kind == "transfer":
            out.transfer_s[program] = mean
        else:
            out.machining_s[(machine, program)] = mean
    return out


def _complete(types: Mapping[str, PartType], d: Durations) -> Durations:
    """``d`` with a guess for every step of ``types`` it has not measured."""
    full = Durations(dict(d.transfer_s), dict(d.machining_s))
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
