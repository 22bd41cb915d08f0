"""The controller's reaction between steps, read from a cell's journal, and where time goes.

A step's **possible start** is the latest of: its part's previous step ended; the machine it
runs on finished its previous step (for a transfer: the robot's previous transfer, and the
mill it loads was unloaded; for a conveyor load, also a pallet could be there: the previous
load's start plus the conveyor's time); its **reaction** is its actual start minus that, in
wall time. The **critical chain** walks back from the step that ended last through the
predecessor that bound each start: the reactions on it are the ones the makespan waited for.
"""

from __future__ import annotations

import statistics
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass

from _common import percentile
from cellctl.cell.config import CONVEYOR, transfer_ends
from cellctl.cell.journal import Step
from cellctl.cell.physics import Physics


@dataclass
class Reactions:
    """Every step's reaction (s, wall) and the sum of those on the critical chain."""

    by_step: list[tuple[Step, float]]
    critical_s: float
    critical_n: int

    def values(self) -> list[float]:
        return [r for _, r in self.by_step]

    def p(self, q: float) -> float:
        return percentile(self.values(), q) if self.by_step else 0.0


def reactions(steps: Sequence[Step], robot: str, conveyor_s: float) -> Reactions:
    """Reactions of the finished ``steps`` (``conveyor_s``: a pallet's wall time)."""
    done = sorted((s for s in steps if s.ended is not None), key=lambda s: s.started)
    last_of_part: dict[str, Step] = {}
    last_on: dict[str, Step] = {}  # machine -> its previous step
    left_mill: dict[str, Step] = {}  # mill -> the transfer that last took a part out of it
    last_load: Step | None = None
    pred: dict[int, Step | None] = {}
    react: dict[int, float] = {}
    out: list[tuple[Step, float]] = []
    for s in done:
        candidates: list[tuple[float, Step | None]] = []
        if s.part_id in last_of_part:
            p = last_of_part[s.part_id]
            candidates.append((p.ended or 0.0, p))
        if s.machine in last_on:
            p = last_on[s.machine]
            candidates.append((p.ended or 0.0, p))
        if s.kind == "transfer":
            source, target = transfer_ends(s.program)
            if target != CONVEYOR and target in left_mill:
                p = left_mill[target]
                candidates.append((p.ended or 0.0, p))
            if source == CONVEYOR and last_load is not None:
                candidates.append((last_load.started + conveyor_s, None))
        if candidates:
            possible, by = max(candidates, key=lambda c: c[0])
            r = max(0.0, s.started - possible)
            pred[s.id], react[s.id] = by, r
            out.append((s, r))
        else:
            pred[s.id], react[s.id] = None, 0.0
        last_of_part[s.part_id] = s
        last_on[s.machine] = s
        if s.kind == "transfer":
            source, _ = transfer_ends(s.program)
            if source != CONVEYOR:
                left_mill[source] = s
            else:
                last_load = s
    critical, n = 0.0, 0
    step: Step | None = max(done, key=lambda s: s.ended or 0.0) if done else None
    while step is not None:
        critical += react.get(step.id, 0.0)
        n += 1
        step = pred.get(step.id)
    return Reactions(out, critical, n)


def breakdown(steps: Sequence[Step], physics: Physics, rx: Reactions) -> list[str]:
    """Lines: per step kind, mean measured duration against its physical one, and the mean
    reaction before it (all wall ms)."""
    measured: dict[str, list[float]] = defaultdict(list)
    before: dict[str, list[float]] = defaultdict(list)
    phys: dict[str, float] = {}
    parts: dict[str, dict[str, float]] = {}
    for s in steps:
        if s.state != "finished" or s.ended is None:
            continue
        key = s.program if s.kind == "transfer" else f"{s.machine} {s.program}"
        measured[key].append(s.ended - s.started)
        t = physics.transfers.get(s.program) if s.kind == "transfer" else None
        m = physics.machining.get((s.machine, s.program)) if s.kind != "transfer" else None
        known = t or m
        if known is not None:
            phys[key], parts[key] = known.seconds, known.parts
    for s, r in rx.by_step:
        key = s.program if s.kind == "transfer" else f"{s.machine} {s.program}"
        before[key].append(r)
    lines = []
    for key, values in sorted(measured.items()):
        mean = statistics.fmean(values)
        p = phys.get(key, 0.0)
        made_of = ", ".join(f"{k} {v * 1e3:.1f}" for k, v in parts.get(key, {}).items())
        wait = statistics.fmean(before[key]) if before.get(key) else 0.0
        lines.append(
            f"  {key:40s} n={len(values):3d} measured {mean * 1e3:9.1f} ms, physical "
            f"{p * 1e3:9.1f} ms ({made_of}), overhead {(mean - p) * 1e3:7.1f} ms "
            f"({(mean / p - 1) if p else 0:+.1%}); reaction before it {wait * 1e3:6.1f} ms"
        )
    return lines
