"""The least makespan of any split of a batch over a factory's cells: the factory's bound.

::

    phys = physical_durations(load_cell("cell1"), time_scale=scale)   # cell.physics
    bounds = {"cell1": physical_bound(config.parts, phys), ...}       # counts per type -> s
    best, split = split_bound(bounds, {"wax-robot-base": 60, "wax-toy-mill-table": 60})
    # best: s; split: {"cell1": {"wax-robot-base": 15, "wax-toy-mill-table": 15}, ...}

A cell's bound is the bottleneck bound (:func:`cellctl.cell.scheduler.resource_bounds`) of the
parts it is given (infinite when they include a type it does not make: cells of different
templates make different types). :func:`physical_bound` takes its durations from what the
machines physically do (:mod:`cellctl.cell.physics`: the machines' own models, never a measured
duration): no cell can beat it, whatever its controller does. :func:`cell_bound` takes the
durations that cell measured (the mean of each robot program and each (mill, program), the
least of each for head and tail), overhead included: how busy the bottleneck was, not how close
to the best possible.

No split of the batch can finish before its busiest cell's bound, so the least, over every way
of dividing each type's count among the cells, of the largest cell bound is a bound on the
factory's makespan. It is found exactly, by a dynamic program over count vectors (cell by cell:
the least largest bound of the first cells for every sub-batch), not by assuming the cells
alike or the bound linear.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping

from cellctl.cell.config import PartType
from cellctl.cell.estimate import Durations
from cellctl.cell.physics import Physics
from cellctl.cell.scheduler import lower_bound

#: A cell's bound (s) of a batch given as parts per type.
CellBound = Callable[[Mapping[str, int]], float]


def cell_bound(types: Mapping[str, PartType], d: Durations) -> CellBound:
    """The bottleneck bound of a cell making ``types`` with measured durations ``d``, per
    batch: the cell's utilization, not a physical limit (see module docstring)."""

    def bound(counts: Mapping[str, int]) -> float:
        parts = [t for t, n in counts.items() for _ in range(n)]
        if not parts:
            return 0.0
        if not set(parts) <= set(types):
            return math.inf  # a type it does not make: never all of this batch
        return lower_bound(
            parts,
            types,
            d.transfer_s,
            d.machining_s,
            least_transfer_s=d.least_transfer_s,
            least_machining_s=d.least_machining_s,
        )

    return bound


def physical_bound(types: Mapping[str, PartType], physics: Physics) -> CellBound:
    """The physical bound (s) of a cell making ``types``, per batch (see module docstring)."""

    def bound(counts: Mapping[str, int]) -> float:
        parts = [t for t, n in counts.items() for _ in range(n)]
        if not set(parts) <= set(types):
            return math.inf  # a type it does not make: never all of this batch
        return physics.bound(parts, types)

    return bound


def split_bound(
    bounds: Mapping[str, CellBound], counts: Mapping[str, int]
) -> tuple[float, dict[str, dict[str, int]]]:
    """The least largest cell bound over every split of ``counts`` among the cells of
    ``bounds``, and one split that reaches it (parts per type per cell)."""
    if not bounds:
        raise ValueError("a split needs at least one cell")
    names = [t for t, n in counts.items() if n > 0]
    full = tuple(counts[t] for t in names)
    # Count vectors as flat indices (mixed radix), so s - t is one subtraction.
    vectors = list(itertools.product(*(range(n + 1) for n in full)))
    strides = [math.prod(n + 1 for n in full[j + 1 :]) for j in range(len(full))]
    cells = list(bounds)
    tables = {c: [bounds[c](dict(zip(names, v, strict=True))) for v in vectors] for c in cells}
    # best[i]: the least largest bound of the cells so far making vectors[i]; picks[k][i]:
    # what cell k makes then.
    best = tables[cells[0]][:]
    picks: list[list[int]] = [list(range(len(vectors)))]
    for k, cell in enumerate(cells[1:], start=1):
        own = tables[cell]
        # Cheapest first: once a cell's own bound reaches the best found, nothing beats it.
        order = sorted(range(len(vectors)), key=own.__getitem__)
        last = k == len(cells) - 1
        wanted = [len(vectors) - 1] if last else range(len(vectors))
        new = [math.inf] * len(vectors)
        pick = [0] * len(vectors)
        for i in wanted:
            s = vectors[i]
            top, choice = math.inf, 0
            for t in order:
                if own[t] >= top:
                    break
                v = vectors[t]
                if any(a > b for a, b in zip(v, s, strict=True)):
                    continue
                value = max(best[i - sum(a * w for a, w in zip(v, strides, strict=True))], own[t])
                if value < top:
                    top, choice = value, t
            new[i], pick[i] = top, choice
        best = new
        picks.append(pick)
    # Walk back from the whole batch to what each cell makes.
    split: dict[str, dict[str, int]] = {}
    i = len(vectors) - 1
    for k in range(len(cells) - 1, -1, -1):
        t = picks[k][i]
        split[cells[k]] = dict(zip(names, vectors[t], strict=True))
        i -= sum(a * w for a, w in zip(vectors[t], strides, strict=True))
    return best[-1], {c: split[c] for c in cells}
