"""The scheduler is pure: parts and the cell's state in, the robot's next transfer out."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.cell.config import PartType, RouteStep
from cellctl.cell.scheduler import PartState, Transfer, lower_bound, next_transfer

TWO_MILLS = PartType(
    "base",
    (
        RouteStep("cnc1", Path("rough.dyn"), "rough", 10, 100.0),
        RouteStep("cnc2", Path("finish.dyn"), "finish", 10, 60.0),
    ),
)
ONE_MILL = PartType("plate", (RouteStep("cnc2", Path("plate.dyn"), "plate", 5, 30.0),))
TYPES = {"base": TWO_MILLS, "plate": ONE_MILL}
MILLS = {"cnc1", "cnc2", "conveyor"}


def part(
    pid: str,
    location: str = "conveyor",
    route_index: int = 0,
    status: str = "waiting",
    *,
    part_type: str = "base",
    priority: int = 0,
    seq: int = 0,
) -> PartState:
    return PartState(pid, part_type, location, route_index, status, priority, seq)


def pick(parts: list[PartState], **kwargs: object) -> Transfer | None:
    options: dict[str, object] = {"mills_in_service": MILLS, "pallet_present": True}
    options.update(kwargs)
    return next_transfer(parts, TYPES, **options)  # type: ignore[arg-type]


def test_loads_the_first_waiting_part_into_its_first_mill() -> None:
    t = pick([part("A-1", seq=1), part("A-2", seq=2)])
    assert t == Transfer("A-1", "conveyor", "cnc1")
    assert t.program == "conveyor_to_cnc1"


def test_unload_comes_before_advance_and_advance_before_load() -> None:
    finished = part("A-1", "cnc2", 2, seq=1)
    roughed = part("A-2", "cnc1", 1, seq=2)
    waiting = part("A-3", seq=3)
    assert pick([waiting, roughed, finished]) == Transfer("A-1", "cnc2", "conveyor")
    # cnc2 still holds A-1 (not finished there yet): A-2 cannot advance, nothing is loaded
    # into cnc1 (occupied by A-2).
    cutting = part("A-1", "cnc2", 1, "active", seq=1)
    assert pick([waiting, roughed, cutting]) is None
    assert pick([waiting, roughed]) == Transfer("A-2", "cnc1", "cnc2")


def test_a_full_outfeed_holds_the_unload_but_not_the_rest() -> None:
    finished = part("A-1", "cnc2", 2, seq=1)
    waiting = part("A-2", seq=2)
    assert pick([finished, waiting], outfeed_clear=False) == Transfer("A-2", "conveyor", "cnc1")


def test_priority_then_arrival_order() -> None:
    parts = [part("A-1", seq=1), part("B-1", seq=2, priority=5), part("C-1", seq=0)]
    assert pick(parts) == Transfer("B-1", "conveyor", "cnc1")
    assert pick([parts[0], parts[2]]) == Transfer("C-1", "conveyor", "cnc1")


def test_no_pallet_no_load() -> None:
    assert pick([part("A-1")], pallet_present=False) is None
    # ... but a finished part is still unloaded.
    assert pick([part("A-1", "cnc2", 2), part("A-2")], pallet_present=False) == Transfer(
        "A-1", "cnc2", "conveyor"
    )


def test_held_part_blocks_its_mill_and_out_of_service_mill_takes_nothing() -> None:
    held = part("A-1", "cnc1", 0, "held", seq=1)
    assert pick([held, part("A-2", seq=2)]) is None
    # A part for another mill still goes.
    plate = part("P-1", seq=3, part_type="plate")
    assert pick([held, part("A-2", seq=2), plate]) == Transfer("P-1", "conveyor", "cnc2")
    assert pick([plate], mills_in_service={"cnc1", "conveyor"}) is None
    roughed = part("A-3", "cnc1", 1)
    assert pick([roughed], mills_in_service={"cnc1", "conveyor"}) is None


def test_done_and_scrapped_parts_do_not_occupy_anything() -> None:
    parts = [part("A-1", "out", 2, "done"), part("A-2", seq=2)]
    assert pick(parts) == Transfer("A-2", "conveyor", "cnc1")


def test_one_at_a_time_waits_for_the_part_in_the_cell() -> None:
    roughed = part("A-1", "cnc2", 1, "active", seq=1)
    waiting = part("A-2", seq=2)
    assert pick([roughed, waiting], one_at_a_time=True) is None
    assert pick([roughed, waiting]) == Transfer("A-2", "conveyor", "cnc1")
    assert pick([waiting], one_at_a_time=True) == Transfer("A-2", "conveyor", "cnc1")


def test_a_mill_never_gets_two_parts() -> None:
    """Whatever the mix, the chosen target is never a place a live part occupies."""
    import itertools

    places = [("conveyor", 0), ("cnc1", 0), ("cnc1", 1), ("cnc2", 1), ("cnc2", 2)]
    for combo in itertools.product(places, repeat=3):
        parts = [part(f"A-{i}", loc, idx, seq=i) for i, (loc, idx) in enumerate(combo, start=1)]
        mills = [p.location for p in parts if p.location != "conveyor"]
        if len(mills) != len(set(mills)):
            continue  # not a physical state
        t = pick(parts)
        if t is not None and t.target != "conveyor":
            assert t.target not in mills, (combo, t)


SHORT = {"conveyor_to_cnc1": 10.0, "cnc1_to_cnc2": 12.0, "cnc2_to_conveyor": 8.0}
CUTS = {("cnc1", "rough"): 100.0, ("cnc2", "finish"): 60.0}


def test_lower_bound_one_part_is_its_whole_route() -> None:
    # One part: cnc1's term = its load + cut + unload + what must follow (cnc2 and its legs).
    assert lower_bound(["base"], TYPES, SHORT, CUTS) == pytest.approx(10 + 100 + 12 + 60 + 8)


def test_lower_bound_is_the_bottleneck_mill_for_a_batch() -> None:
    n = 5
    bound = lower_bound(["base"] * n, TYPES, SHORT, CUTS)
    cnc1 = n * (10 + 100 + 12) + (60 + 8)  # no head; tail is cnc2's cut and the unload
    robot = n * (10 + 12 + 8)
    assert bound == pytest.approx(max(cnc1, robot))
    assert bound == pytest.approx(cnc1)


def test_lower_bound_robot_bound_when_cuts_are_short() -> None:
    cuts = {("cnc1", "rough"): 1.0, ("cnc2", "finish"): 1.0}
    n = 4
    assert lower_bound(["base"] * n, TYPES, SHORT, cuts) == pytest.approx(n * 30.0)


def test_lower_bound_mixed_types_counts_head_of_a_later_mill() -> None:
    transfer_s = {**SHORT, "conveyor_to_cnc2": 9.0}
    cuts = {**CUTS, ("cnc2", "plate"): 30.0}
    bound = lower_bound(["base", "plate"], TYPES, transfer_s, cuts)
    # cnc2: head = least time before a part reaches it = 0 (the plate goes straight there);
    # work = base (12 + 60 + 8) + plate (9 + 30 + 8); tail 0.
    cnc2 = 12 + 60 + 8 + 9 + 30 + 8
    cnc1 = 10 + 100 + 12 + (60 + 8)
    robot = 10 + 12 + 8 + 9 + 8
    assert bound == pytest.approx(max(cnc1, cnc2, robot))
