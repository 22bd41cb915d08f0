"""The factory's dispatch by the cells' own plans (``[dispatch] estimate = "plan"``): the pure
functions of :mod:`cellctl.factory.dispatch` over what the cells said, and factory.toml's
``[dispatch]`` table. The end-to-end run is tests/test_factory_plan_dispatch.py."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.errors import UsageError
from cellctl.factory.config import load_factory
from cellctl.factory.dispatch import (
    BOUND,
    PLAN,
    SKEW_S,
    Estimating,
    candidates,
    choose,
    estimate_s,
    finish_s,
    load_s,
    plan_load_s,
)
from cellctl.factory.store import ACCEPTED, QUEUED, SENT, CellSeen, FactoryOrder

NOW = 1_800_000_000.0
TYPES = ("base", "table")


def cell(
    name: str,
    *,
    bound: float = 0.0,
    plan: tuple[float, float] | None = None,
    bounds: dict[str, float] | None = None,
    status: str = "online",
    paused: bool = False,
    state_time: float = NOW - 1,
) -> CellSeen:
    """A cell as the factory last heard it: ``plan`` is (planned_at, plan_finish_s)."""
    state: dict[str, Any] = {
        "part_types": {t: {"bound_s": b} for t, b in (bounds or {"base": 10.0}).items()},
        "finish_estimate_s": bound,
        "paused": paused,
    }
    if plan is not None:
        state["planned_at"], state["plan_finish_s"] = plan
    return CellSeen(name, status, NOW - 5, state, state_time)


def order(
    oid: str,
    part_type: str = "base",
    qty: int = 1,
    *,
    state: str = QUEUED,
    cell: str | None = None,
    accepted: float | None = None,
    refused: tuple[str, ...] = (),
) -> FactoryOrder:
    return FactoryOrder(
        oid,
        part_type,
        qty,
        0,
        state,
        cell,
        "",
        NOW - 100,
        NOW - 100,
        None,
        None,
        0,
        None,
        accepted,
        None,
        None,
        refused,
        0,
        0,
        0,
    )


PLANS = Estimating(PLAN, NOW, plan_age=600.0)


def test_a_fresh_plan_counts_its_finish_less_the_time_gone_and_orders_given_since() -> None:
    c = cell("c1", bound=50.0, plan=(NOW - 100, 400.0))
    assert estimate_s(c, [], PLANS) == (300.0, PLAN)  # planned 100 s ago: 300 s left
    assert estimate_s(c, [], Estimating(BOUND, NOW)) == (50.0, BOUND)
    given_since = [
        order("S", qty=2, state=SENT, cell="c1"),  # sent, not yet answered
        order("A", qty=1, state=ACCEPTED, cell="c1", accepted=NOW - 50),  # after the plan
        order("P", qty=5, state=ACCEPTED, cell="c1", accepted=NOW - 200),  # in the plan
        order("O", qty=7, state=SENT, cell="c2"),  # another cell's
    ]
    assert plan_load_s(c, given_since, NOW, 600.0) == 300.0 + 3 * 10.0
    # A plan whose finish is past counts nothing left, but what was given since.
    done = cell("c1", plan=(NOW - 500, 100.0))
    assert estimate_s(done, given_since[:1], PLANS) == (20.0, PLAN)


def test_a_stale_absent_or_future_plan_falls_back_to_the_bound() -> None:
    for plan in (None, (NOW - 601, 10.0), (NOW + SKEW_S + 1, 10.0)):
        assert estimate_s(cell("c1", bound=50.0, plan=plan), [], PLANS) == (50.0, BOUND)
    # Within the skew a plan a little ahead of the factory's clock still counts.
    assert estimate_s(cell("c1", bound=50.0, plan=(NOW + 1, 10.0)), [], PLANS) == (11.0, PLAN)


def test_the_why_says_which_estimate_chose_the_cell() -> None:
    # c1's bound is the lower, but its plan (a machine down: its work does not finish soon)
    # is far later than c2's.
    cells = {
        "c1": cell("c1", bound=20.0, plan=(NOW - 10, 5000.0)),
        "c2": cell("c2", bound=60.0, plan=(NOW - 10, 70.0)),
    }
    o = order("N", qty=2)
    assert choose(o, cells, []) == ("c1", "c1 finishes it earliest by its bound: 40 s")
    assert choose(o, cells, [], PLANS) == ("c2", "c2 finishes it earliest by its plan: 80 s")
    cells["c2"] = cell("c2", bound=60.0)  # no plan: counted by its bound, against c1's plan
    assert choose(o, cells, [], PLANS) == ("c2", "c2 finishes it earliest by its bound: 80 s")


def test_dispatch_reads_its_table_from_factory_toml(tmp_path: Path) -> None:
    base = (
        '[broker]\nurl = "mqtt://127.0.0.1:1883"\ncredentials = "c"\n\n'
        '[cells.c1]\nprefix = "p/c1"\n'
    )
    (tmp_path / "factory.toml").write_text(base)
    config = load_factory(tmp_path)
    assert (config.estimate, config.plan_age) == (BOUND, 600.0)
    (tmp_path / "factory.toml").write_text(
        base + '\n[dispatch]\nestimate = "plan"\nplan_age = 90\n'
    )
    config = load_factory(tmp_path)
    assert (config.estimate, config.plan_age) == (PLAN, 90.0)
    (tmp_path / "factory.toml").write_text(base + '\n[dispatch]\nestimate = "means"\n')
    with pytest.raises(UsageError, match=r"dispatch\.estimate"):
        load_factory(tmp_path)


# -- the property: the chosen cell has the least estimated finish among those it may go to --

_times = st.floats(0, 10_000, allow_nan=False, allow_infinity=False)
_cell = st.fixed_dictionaries(
    {
        "bound": _times,
        "plan": st.none() | st.tuples(st.floats(NOW - 2000, NOW + 20), _times),
        "bounds": st.dictionaries(st.sampled_from(TYPES), st.floats(0, 500), min_size=1),
        "status": st.sampled_from(["online", "online", "offline"]),
        "paused": st.booleans(),
        "state_time": st.floats(NOW - 2000, NOW),
    }
)
_given = st.lists(
    st.tuples(
        st.integers(0, 4),
        st.sampled_from(TYPES),
        st.integers(1, 20),
        st.sampled_from([SENT, ACCEPTED]),
        st.floats(NOW - 2000, NOW),
    ),
    max_size=8,
)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(_cell, min_size=1, max_size=5),
    _given,
    st.sampled_from(TYPES),
    st.integers(1, 50),
    st.sampled_from([BOUND, PLAN]),
    st.floats(1, 3000),
    st.lists(st.integers(0, 4), max_size=2),
)
def test_the_chosen_cell_has_the_least_estimated_finish_among_makers(
    said: list[dict[str, Any]],
    given_orders: list[tuple[int, str, int, str, float]],
    part_type: str,
    qty: int,
    estimate: Any,
    age: float,
    refused: list[int],
) -> None:
    cells = {f"c{i}": cell(f"c{i}", **fields) for i, fields in enumerate(said)}
    open_orders = [
        order(f"G{n}", t, q, state=s, cell=f"c{i}", accepted=when if s == ACCEPTED else None)
        for n, (i, t, q, s, when) in enumerate(given_orders)
        if f"c{i}" in cells
    ]
    o = order("N", part_type, qty, refused=tuple(f"c{i}" for i in refused))
    how = Estimating(estimate, NOW, age)
    chosen, why = choose(o, cells, open_orders, how)
    may, _ = candidates(o, cells)
    if chosen is None:
        assert not may and why
        # None online, not refused, makes it.
        assert not [
            c
            for c in cells.values()
            if part_type in c.part_types and c.status == "online" and c.name not in o.refused
        ]
        return
    best, kind = finish_s(o, cells[chosen], open_orders, how)
    assert chosen in {c.name for c in may}
    assert all(best <= finish_s(o, c, open_orders, how)[0] + 1e-6 for c in may)
    assert why == f"{chosen} finishes it earliest by its {kind}: {best:.0f} s"
    # By the bound the plans change nothing; by the plan a fresh one is what counted.
    if estimate == BOUND:
        assert (
            kind == BOUND
            and best
            == load_s(cells[chosen], open_orders) + qty * cells[chosen].part_types[part_type]
        )
    else:
        assert (kind == PLAN) == (plan_load_s(cells[chosen], open_orders, NOW, age) is not None)
    # A paused cell only when every one it may go to is paused.
    if cells[chosen].state["paused"]:
        assert all(c.state["paused"] for c in may)


def test_a_cell_with_a_machine_of_the_route_out_is_passed_over_by_plan_or_bound() -> None:
    """An idle cell with a machine the part type needs out of service would have the order
    stuck: it is no candidate, whatever its plan or bound says; when no cell can, the order
    waits and the why names each cell."""
    machines = {"robot": True, "cnc1": True, "cnc2": False}
    down = cell("c1", plan=(NOW - 1, 0.0))  # idle: its plan says 0
    down.state["machines"] = {m: {"in_service": up} for m, up in machines.items()}
    down.state["part_types"] = {
        "base": {"bound_s": 10.0, "machines": ["robot", "cnc1", "cnc2"]},
        "table": {"bound_s": 10.0, "machines": ["robot", "cnc1"]},
    }
    busy = cell("c2", bound=500.0, plan=(NOW - 1, 500.0), bounds={"base": 10.0, "table": 10.0})
    cells = {"c1": down, "c2": busy}
    for how in (PLANS, Estimating(BOUND, NOW)):
        assert choose(order("A"), cells, [], how)[0] == "c2"
        assert choose(order("T", "table"), cells, [], how)[0] == "c1"  # cnc2 not on its route
    alone = {"c1": down}
    assert candidates(order("A"), alone) == (
        [],
        "waiting for a cell that can make base now (c1 has cnc2 out of service)",
    )
    # A cell whose state does not say what a part type needs: every machine counts.
    del down.state["part_types"]["table"]["machines"]
    assert choose(order("T", "table"), cells, [], PLANS)[0] == "c2"
