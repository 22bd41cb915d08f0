"""The factory's bound: the least makespan of any split of a batch over the cells, against
every split tried one by one, and durations read from journal steps."""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.cell.config import PartType, RouteStep
from cellctl.cell.estimate import measured_durations
from cellctl.cell.journal import Step
from cellctl.factory.bound import CellBound, cell_bound, split_bound

BASE = PartType(
    "base",
    (
        RouteStep("cnc1", Path("base_rough.dyn"), "base_rough", 10, 100.0),
        RouteStep("cnc2", Path("base_finish.dyn"), "base_finish", 10, 60.0),
    ),
)
TABLE = PartType(
    "table",
    (
        RouteStep("cnc1", Path("table_rough.dyn"), "table_rough", 10, 100.0),
        RouteStep("cnc2", Path("table_finish.dyn"), "table_finish", 10, 60.0),
    ),
)
TYPES = {"base": BASE, "table": TABLE}


def affine(start: float, per: Mapping[str, float]) -> CellBound:
    """A made-up cell: a start-up time, then seconds per part of each type."""
    return lambda counts: (
        start + sum(per[t] * n for t, n in counts.items()) if any(counts.values()) else 0.0
    )


def every_split(bounds: Mapping[str, CellBound], counts: Mapping[str, int]) -> float:
    """The least largest cell bound, trying each split in turn."""
    cells = list(bounds)
    types = list(counts)
    best = float("inf")
    shares = {
        t: [
            c
            for c in itertools.product(range(counts[t] + 1), repeat=len(cells))
            if sum(c) == counts[t]
        ]
        for t in types
    }
    for combo in itertools.product(*(shares[t] for t in types)):
        worst = max(
            bounds[cell]({t: combo[j][i] for j, t in enumerate(types)})
            for i, cell in enumerate(cells)
        )
        best = min(best, worst)
    return best


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(0, 5), st.floats(0.5, 10), st.floats(0.5, 10)),
        min_size=1,
        max_size=3,
    ),
    st.integers(0, 4),
    st.integers(0, 4),
)
def test_the_split_bound_is_the_least_of_every_split(
    cells: list[tuple[float, float, float]], bases: int, tables: int
) -> None:
    bounds = {f"cell{i}": affine(s, {"base": a, "table": b}) for i, (s, a, b) in enumerate(cells)}
    counts = {"base": bases, "table": tables}
    best, split = split_bound(bounds, counts)
    assert best == every_split(bounds, counts)
    # The split it gives makes the whole batch and reaches that bound.
    for t, n in counts.items():
        assert sum(share.get(t, 0) for share in split.values()) == n
    assert max(bounds[c](share) for c, share in split.items()) == best


def test_a_slower_cell_gets_fewer_parts() -> None:
    bounds = {
        "fast": affine(0, {"base": 1, "table": 1}),
        "slow": affine(0, {"base": 2, "table": 2}),
    }
    best, split = split_bound(bounds, {"base": 6, "table": 3})
    assert best == 6
    assert sum(split["fast"].values()) == 6 and sum(split["slow"].values()) == 3


def step(kind: str, machine: str, program: str, start: float, end: float) -> Step:
    return Step(0, "P1", kind, machine, program, "finished", start, end, "", 1)


def test_measured_durations_feed_the_cells_bottleneck_bound() -> None:
    steps = [
        step("transfer", "robot", "conveyor_to_cnc1", 0, 1),
        step("transfer", "robot", "conveyor_to_cnc1", 10, 13),
        step("machining", "cnc1", "base_rough", 1, 6),
        step("transfer", "robot", "cnc1_to_cnc2", 6, 7),
        step("machining", "cnc2", "base_finish", 7, 15),
        step("transfer", "robot", "cnc2_to_conveyor", 15, 16),
        Step(0, "P2", "machining", "cnc1", "base_rough", "failed", 20, 21, "", 1),
    ]
    d = measured_durations(steps)
    assert d.transfer_s["conveyor_to_cnc1"] == 2 and d.least_transfer_s["conveyor_to_cnc1"] == 1
    assert d.machining_s == {("cnc1", "base_rough"): 5, ("cnc2", "base_finish"): 8}
    bound = cell_bound(TYPES, d)
    # Three bases, by hand from the bottleneck bound (means for the work, least for head and
    # tail): the robot does 3 x (2 + 1 + 1) = 12 s of transfers. CNC 1 has nothing before it,
    # 3 x (load 2 + cut 5 + advance 1) = 24 s, and after it at least advance 1 + cut 8 +
    # unload 1 ... of which the advance is its own: tail = cut 8 + unload 1 = 9 s: 33 s.
    # CNC 2: head = least load 1 + cut 5 = 6 s, 3 x (advance 1 + cut 8 + unload 1) = 30 s,
    # nothing after: 36 s, the bound.
    assert bound({"base": 3, "table": 0}) == 36
    # One base: CNC 1's 8 + 9 = 17 s beats CNC 2's 6 + 10 = 16 s and the robot's 4 s.
    assert bound({"base": 1}) == 17
    assert bound({"base": 0}) == 0.0


def test_cells_of_different_types_are_each_given_their_own() -> None:
    """A cell that does not make a type (cells of different templates) is never given it:
    its bound of a batch with that type is infinite, the best split gives it elsewhere."""
    d = measured_durations(
        [
            step("transfer", "robot", "conveyor_to_cnc1", 0, 1),
            step("machining", "cnc1", "base_rough", 1, 6),
            step("transfer", "robot", "cnc1_to_cnc2", 6, 7),
            step("machining", "cnc2", "base_finish", 7, 15),
            step("transfer", "robot", "cnc2_to_conveyor", 15, 16),
        ]
    )
    only_bases = cell_bound({"base": BASE}, d)
    assert only_bases({"base": 1, "table": 1}) == float("inf")
    assert only_bases({"base": 1, "table": 0}) < float("inf")
    bounds = {"bases": only_bases, "any": affine(0, {"base": 100, "table": 2})}
    best, split = split_bound(bounds, {"base": 2, "table": 3})
    assert split["bases"] == {"base": 2, "table": 0} and split["any"]["table"] == 3
    assert best == max(only_bases({"base": 2}), 6)
