"""A factory of cells played for a week on virtual time: how fast, and how faithful.

Setup (issue 22): ``--cells`` (16) copies of the example cell (robot, CNC 1 roughing, CNC 2
finishing, PLC), each with a week's orders (``--days`` 7 from Monday 06:00; lots of 5, the
two part types taking turns, every third lot rush work, more than a cell can finish), and one
fault window in the first cell (CNC 2 down Monday 10:00 to 11:00). Each cell's plan is played
as ``cellctl plan --dir`` plays it (:func:`cellctl.plan.run.play`: the real controller, its
drivers and the emulators over ``mem://`` on a clock that jumps), the cells side by side in
``--workers`` processes (default: one per core); the factory's own dispatch is not played
(each cell has its orders already).

Then the first cell's first ``--real-minutes`` (30) of machine time run in real time through
real links (bench/plan_shift.py's check: pty, RFC 2217, Modbus/TCP, machines ``--time-scale``
times faster than life) and are compared with its plan.

Figures (last line machine-readable):

- ``sim_hours``: machine hours played, over every cell;
- ``wall_s``: real seconds for every plan (goal <= 60 s, the issue's); ``speedup`` = machine
  seconds played / wall seconds; ``cpu_s``: CPU seconds of every plan (what a shared box's
  load does not inflate);
- ``makespan_delta``: as bench/plan_shift.py's, for the first cell: (real makespan - plan
  makespan) / plan makespan over the steps the real run finished in its window; goal |delta|
  <= 2 %; ``same_order``: those steps started in the same order.

Timing figures on a loaded machine are noisy (the box is shared): say so when you quote them.
Develop with small counts (``--cells 2 --days 0.05 --no-real``).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from datetime import datetime
from pathlib import Path

from _common import machine_line
from cellctl.cell.journal import Step
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.plan.engine import FaultWindow, PlanInputs, PlanOrder
from cellctl.plan.run import play
from plan_shift import LOT, TYPES, key, real_window, window_makespan

#: The issue's goals.
GOAL_WALL_S = 60.0
GOAL_DELTA = 0.02
#: Parts ordered per cell per hour of the plan: about what a cell makes (a cell finishes a
#: week's 672 parts in some 158 h, busy all the while).
PARTS_PER_HOUR = 4


def cell_inputs(cell: int, days: float) -> PlanInputs:
    """Cell ``cell``'s week: its lots, and the fault window if it is the first cell."""
    start = datetime(2026, 11, 23, 6, 0).timestamp()  # a Monday
    parts = max(1, round(PARTS_PER_HOUR * days * 24))
    orders, i = [], 0
    while parts > 0:
        qty = min(LOT, parts)
        orders.append(
            PlanOrder(f"C{cell}-O{i + 1}", TYPES[(i + cell) % 2], qty, 1 if i % 3 == 2 else 0)
        )
        parts -= qty
        i += 1
    until = start + days * 86400
    down = FaultWindow("cnc2", "down", start + 4 * 3600, start + 5 * 3600)
    faults = (down,) if cell == 1 and down.start < until else ()
    return PlanInputs(EXAMPLE_CELL, tuple(orders), start, until, faults=faults, seed=cell)


def play_cell(
    cell: int, days: float, workdir: str
) -> tuple[int, float, float, int, int, list[Step]]:
    """Cell ``cell``'s plan: (cell, machine seconds played, CPU seconds, parts made, orders
    late, its steps)."""
    cpu = time.process_time()
    inputs = cell_inputs(cell, days)
    result = play(inputs, ("default",), Path(workdir) / f"cell{cell}")
    [report] = result.reports
    steps = [
        Step(0, s["part_id"], s["kind"], s["machine"], s["program"], s["state"], s["started"],
             s["ended"], "", 1)
        for s in report.steps
    ]  # fmt: skip
    made = sum(report.parts_made.values())
    return cell, report.ended - report.start, time.process_time() - cpu, made, report.late, steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cells", type=int, default=16, help="Cells in the factory.")
    parser.add_argument("--days", type=float, default=7.0, help="Days planned from Monday 06:00.")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="Processes.")
    parser.add_argument(
        "--real-minutes", type=float, default=30.0, help="Machine minutes run in real time."
    )
    parser.add_argument("--time-scale", type=float, default=50.0, help="The real run's scale.")
    parser.add_argument("--no-real", action="store_true", help="Leave the real-time run out.")
    args = parser.parse_args()
    first = cell_inputs(1, args.days)
    window = ", cnc2 of cell 1 down Monday 10:00-11:00" if first.faults else ""
    print(
        f"plan: {args.cells} cells for {args.days:g} days from Monday 06:00, "
        f"{len(first.orders)} orders each{window}; {args.workers} worker processes"
    )
    with tempfile.TemporaryDirectory(prefix="plan-factory-") as tmp:
        wall = time.monotonic()
        with ProcessPoolExecutor(max_workers=args.workers) as pool:
            futures = [
                pool.submit(play_cell, cell, args.days, tmp) for cell in range(1, args.cells + 1)
            ]
            results = sorted(f.result() for f in futures)
        wall_s = time.monotonic() - wall
        sim_s = sum(r[1] for r in results)
        cpu_s = sum(r[2] for r in results)
        for cell, played, cpu, made, late, _ in results:
            print(f"  cell {cell}: {played / 3600:.2f} h played, {made} parts, {late} orders late, "
                  f"{cpu:.1f} s of CPU")  # fmt: skip
        print(
            f"plan: {sim_s / 3600:.2f} machine hours in {wall_s:.1f} s wall (goal <= "
            f"{GOAL_WALL_S:g} s: {wall_s / GOAL_WALL_S:.2f} of it), {cpu_s:.1f} s of CPU"
        )
        delta, same = float("nan"), False
        if not args.no_real:
            steps, wall_start = asyncio.run(
                real_window(Path(tmp) / "real", first, args.real_minutes, args.time_scale)
            )
            horizon = wall_start + args.real_minutes * 60 / args.time_scale
            keys = {key(s) for s in steps if s.ended is not None and s.ended <= horizon}
            plan_steps = results[0][5]
            missing = keys - {key(s) for s in plan_steps if s.ended is not None}
            if keys and not missing:
                real_s, real_order = window_makespan(steps, keys, args.time_scale)
                plan_s, plan_order = window_makespan(plan_steps, keys, 1.0)
                delta = (real_s - plan_s) / plan_s
                same = real_order == plan_order
                print(
                    f"cell 1, first {args.real_minutes:g} min: {len(keys)} steps; makespan real "
                    f"{real_s:.1f} s, plan {plan_s:.1f} s: delta {delta:+.2%} (goal within "
                    f"{GOAL_DELTA:.0%}); same order: {same}"
                )
            else:
                print(f"cell 1: steps not in the plan: {sorted(missing)}")
    print(
        machine_line(
            sim_hours=sim_s / 3600,
            wall_s=wall_s,
            speedup=sim_s / wall_s,
            makespan_delta=delta,
            same_order=int(same),
            cpu_s=cpu_s,
        )
    )


if __name__ == "__main__":
    main()
