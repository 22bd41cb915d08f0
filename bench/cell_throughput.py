"""A 50-part mixed batch through the emulated example cell: makespan against physics.

The example cell (robot, CNC 1 roughing, CNC 2 finishing, PLC) is emulated in a second
process at one fixed time factor (``--time-scale``, default 100: every machine time and every
character's time on the line is divided by it, so transfer and machining keep their real
proportions). The real controller runs the batch, in lots of ``--lot`` parts alternating
between the cell's part types, twice: with the cellctl schedule, and one part at a time (the
source's way, ``ControllerOptions(one_at_a_time=True)``; ``--no-baseline`` leaves it out).

The limit is the **physical bound** (:mod:`cellctl.cell.physics`): the bottleneck bound of
:func:`cellctl.cell.scheduler.resource_bounds` over durations taken from what the machines
physically do, from the emulators' own models at this time scale, never from the run: each
mill program's cut time from its toolpath and feeds (the DYNALAN machine model the mill
emulator executes), each block's characters at the line rate, the door closing before a cut,
each robot program's motion (the arm's model the robot emulator runs) with the PLC's door
and vise times its WAITIs meet, and each robot program's download once::

    makespan >= max( robot: downloads + sum over parts of all its transfers,
                     each mill M: head(M) + sum over parts routed through M of
                              (load transfer into M + machining on M + unload transfer out of M)
                              + tail(M) )

The makespan runs from the first step's start to the last step's end. Printed figures:

- ``ratio_physical`` = makespan / physical bound (goal <= 1.05 at time scale 100): everything
  the controller adds (its reaction between steps, its polling inside steps) is in it.
- ``utilization`` = makespan / the same bound over the durations this run measured (the mean
  of each step, the least for head and tail): how busy the bottleneck was, overhead included.
  It was printed as ``ratio`` before.
- ``reaction_ms_p50`` / ``reaction_ms_p99``: the controller's reaction between steps, wall ms,
  nearest rank over every step that had a predecessor: from the step's possible start (its
  part's previous step ended, its machine free, for a load a pallet possible) to its start
  (see ``bench/_reaction.py``).
- ``ratio_real``: the same batch with those reactions taking their wall time at scale 1, as
  they would in a real cell. With ``R`` the sum of reactions (wall s) on the critical chain
  (back from the last step through the predecessor that bound each start), ``s`` the time
  scale and ``bound`` the physical bound (wall s at this scale)::

      ratio_real = (makespan * s - R * s + R) / (bound * s)

  Only the reactions between steps are taken back to scale 1; the controller's time inside a
  step (its polls) stays scaled, as it is measured.
- a breakdown per step kind: measured mean against its physical time (and what that is made
  of), and the mean reaction before it; the speed-up over one part at a time; each machine's
  utilization; each mill's idle time; and, from the emulated mills' own execution logs, that
  every physical part was cut exactly once on every mill of its route. Gantt charts go to
  ``--out``. At the defaults the bench takes about 20 minutes (7 without the baseline).
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import multiprocessing as mp
import os
import shutil
import signal
import statistics
import tempfile
import time
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from _common import machine_line
from _reaction import breakdown, reactions
from cellctl.cell.config import CellConfig, load_cell
from cellctl.cell.controller import CellController, ControllerOptions
from cellctl.cell.journal import Step, open_journal
from cellctl.cell.physics import physical_durations
from cellctl.cell.report import Summary, summarize, write_gantt
from cellctl.cell.scheduler import lower_bound
from cellctl.emulators.cell import EXAMPLE_CELL, EmulatedCell
from cellctl.mailbox import open_mailbox
from cellctl.protocol.plc import PlcTiming

PHYSICAL_GOAL = 1.05
REAL_GOAL = 1.01
SPEEDUP_GOAL = 1.8


def _cell_child(conn: Any, directory: str, time_scale: float) -> None:
    """In the child: serve the emulated cell until told to stop, then send its cut log."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    async def serve() -> None:
        cell = EmulatedCell(time_scale=time_scale)
        try:
            await cell.start(Path(directory))
            conn.send("ready")
            loop = asyncio.get_running_loop()
            await loop.run_in_executor(None, conn.recv)
            conn.send(cell.runs_per_part())
        finally:
            await cell.close()

    asyncio.run(serve())


class CellProcess:
    """The emulated cell in another process (its own core, as a real cell's machines are)."""

    def __init__(self, directory: Path, time_scale: float) -> None:
        ctx = mp.get_context("fork")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(
            target=_cell_child, args=(child, str(directory), time_scale), daemon=True
        )
        self.proc.start()
        if not self.conn.poll(60) or self.conn.recv() != "ready":
            raise RuntimeError("the emulated cell did not start")

    def stop(self) -> dict[str, dict[str, int]]:
        """Stop the cell; return how many programs each mill ran per physical part."""
        self.conn.send("stop")
        runs: dict[str, dict[str, int]] = self.conn.recv() if self.conn.poll(30) else {}
        self.proc.join(10)
        if self.proc.is_alive():
            os.kill(self.proc.pid or 0, signal.SIGKILL)
        return runs


@dataclass
class Run:
    """One batch run: figures, finished steps, and the emulated mills' cut log."""

    summary: Summary
    steps: list[Step]
    runs_per_part: dict[str, dict[str, int]]
    config: CellConfig
    gantt: Path


def batch_orders(types: list[str], parts: int, lot: int) -> list[tuple[str, int]]:
    """``parts`` parts in lots of ``lot``, the part types taking turns."""
    orders = []
    left = parts
    i = 0
    while left > 0:
        qty = min(lot, left)
        orders.append((types[i % len(types)], qty))
        left -= qty
        i += 1
    return orders


async def run_batch(
    directory: Path, time_scale: float, orders: list[tuple[str, int]], one_at_a_time: bool
) -> Run:
    """Emulate the cell in ``directory`` (emptied first) and run ``orders`` through it."""
    shutil.rmtree(directory, ignore_errors=True)
    cell = CellProcess(directory, time_scale)
    runs: dict[str, dict[str, int]] = {}
    try:
        mailbox = open_mailbox(directory)
        prefix = "S" if one_at_a_time else "O"
        for i, (part, qty) in enumerate(orders, start=1):
            mailbox.post_order(part, qty, order_id=f"{prefix}{i}")
        mailbox.close()
        config = load_cell(directory)
        options = ControllerOptions.from_config(config, one_at_a_time=one_at_a_time)
        controller = CellController(
            config, open_journal(directory), open_mailbox(directory), options=options
        )
        started = time.time()
        try:
            await controller.connect()
            await controller.run(asyncio.Event(), until_idle=True)
        finally:
            await controller.close()
    finally:
        runs = cell.stop()
    machines = [config.robot.name, *(m.name for m in config.mills)]
    journal = controller.journal
    summary = summarize(journal, machines, since=started)
    title = "one part at a time" if one_at_a_time else "cellctl schedule"
    gantt = write_gantt(
        journal,
        machines,
        directory / "gantt.svg",
        since=started,
        title=f"{title}: makespan {summary.makespan_s:.1f} s (time scale {time_scale:g})",
    )
    steps = [s for s in journal.steps() if s.started >= started and s.ended is not None]
    return Run(summary, steps, runs, config, gantt)


def measured_durations(
    steps: list[Step],
) -> tuple[dict[str, list[float]], dict[tuple[str, str], list[float]]]:
    """Durations per robot program and per (mill, mill program), from finished steps."""
    durations: dict[str, list[float]] = defaultdict(list)
    cuts: dict[tuple[str, str], list[float]] = defaultdict(list)
    for s in steps:
        if s.state != "finished" or s.ended is None:
            continue
        if s.kind == "transfer":
            durations[s.program].append(s.ended - s.started)
        else:
            cuts[(s.machine, s.program)].append(s.ended - s.started)
    return dict(durations), dict(cuts)


def mill_idle(steps: list[Step], mill: str) -> tuple[float, list[float]]:
    """Time ``mill`` was neither loaded, machining nor unloaded between its first and last step.

    Returns the total and the gaps, longest first.
    """
    spans = []
    for s in steps:
        if s.ended is None:
            continue
        ends = s.program.split("_to_") if s.kind == "transfer" else []
        if s.machine == mill or mill in ends:
            spans.append((s.started, s.ended))
    spans.sort()
    gaps = []
    reach = spans[0][1] if spans else 0.0
    for start, end in spans[1:]:
        if start > reach:
            gaps.append(start - reach)
        reach = max(reach, end)
    gaps.sort(reverse=True)
    return sum(gaps), gaps


def robot_wait(steps: list[Step], robot: str) -> float:
    """Sum of gaps between consecutive robot steps (dispatch latency plus real waits)."""
    spans = sorted((s.started, s.ended) for s in steps if s.machine == robot and s.ended)
    return sum(max(0.0, b[0] - a[1]) for a, b in itertools.pairwise(spans))


def cut_check(run: Run, part_list: list[str]) -> tuple[bool, str]:
    """Every physical part cut exactly once on each mill of its route (emulators' own logs)."""
    expected = Counter(
        frozenset(Counter(s.mill for s in run.config.parts[t].route).items()) for t in part_list
    )
    seen = Counter(frozenset(r.items()) for r in run.runs_per_part.values())
    per_mill = Counter(
        m for r in run.runs_per_part.values() for m, n in r.items() for _ in range(n)
    )
    text = (
        f"{len(run.runs_per_part)} physical parts; programs run on them: "
        + ", ".join(f"{m} {n}" for m, n in sorted(per_mill.items()))
        + f"; cut exactly once per mill of the route: {'yes' if seen == expected else 'NO'}"
    )
    return seen == expected, text


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--parts", type=int, default=50)
    parser.add_argument("--time-scale", type=float, default=100.0)
    parser.add_argument("--lot", type=int, default=5, help="Parts per order (types alternate).")
    parser.add_argument(
        "--no-baseline", action="store_true", help="Leave out the one-at-a-time run."
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path(tempfile.gettempdir()) / "cellctl-cell-throughput",
        help="Where the emulated cells, journals and Gantt charts go.",
    )
    args = parser.parse_args()
    scale = args.time_scale
    types = list(load_cell(EXAMPLE_CELL).parts)
    orders = batch_orders(types, args.parts, args.lot)
    part_list = [t for t, qty in orders for _ in range(qty)]
    print(
        f"batch: {args.parts} parts ("
        + ", ".join(f"{n} x {t}" for t, n in Counter(part_list).items())
        + f") in {len(orders)} orders of <= {args.lot}, types alternating; time scale {scale:g}"
    )
    sched = await run_batch(args.out / "cellctl", scale, orders, one_at_a_time=False)
    base = None
    if not args.no_baseline:
        base = await run_batch(args.out / "one-at-a-time", scale, orders, one_at_a_time=True)

    # The limit: physics, from the machines' models at this time scale.
    config = sched.config
    options = ControllerOptions.from_config(config)
    physics = physical_durations(config, time_scale=scale, done_output=options.done_output)
    terms = physics.terms(part_list, config.parts)
    bound = max(terms.values())
    print(
        "physical bound terms (robot: downloads + all transfers; mill: head + loads, cuts, "
        "unloads + tail): " + ", ".join(f"{k} {v:.2f} s" for k, v in terms.items())
    )

    # Today's figure, renamed: the same bound over this run's measured durations.
    transfers, cuts = measured_durations(sched.steps)
    if not transfers or not cuts:
        raise SystemExit(f"no finished steps in {args.out / 'cellctl'}: see its journal")
    transfer_s = {k: statistics.fmean(v) for k, v in transfers.items()}
    machining_s = {k: statistics.fmean(v) for k, v in cuts.items()}
    least_t = {k: min(v) for k, v in transfers.items()}
    least_m = {k: min(v) for k, v in cuts.items()}
    measured = (part_list, config.parts, transfer_s, machining_s)
    busy_bound = lower_bound(*measured, least_transfer_s=least_t, least_machining_s=least_m)

    robot = config.robot.name
    s = sched.summary
    made = sum(s.parts_made.values())
    conveyor = PlcTiming().conveyor_s / scale
    rx = reactions(sched.steps, robot, conveyor)
    print("where the time goes, per step kind (wall ms; overhead = measured - physical):")
    for line in breakdown(sched.steps, physics, rx):
        print(line)
    print(f"physical bound: {bound:.2f} s ({bound * scale / 3600:.2f} h in the real cell)")
    print(f"makespan, cellctl schedule: {s.makespan_s:.2f} s  ({made} parts made)")
    ratio_physical = s.makespan_s / bound if bound > 0 else float("inf")
    verdict = "meets" if ratio_physical <= PHYSICAL_GOAL else "MISSES"
    print(
        f"ratio_physical = makespan / physical bound: {ratio_physical:.4f} "
        f"(goal <= {PHYSICAL_GOAL} at time scale 100: {verdict})"
    )
    utilization = s.makespan_s / busy_bound if busy_bound > 0 else float("inf")
    print(
        f"utilization = makespan / bound from this run's measured durations ({busy_bound:.2f} s):"
        f" {utilization:.4f} (the old 'ratio')"
    )
    r_p50, r_p99 = rx.p(50), rx.p(99)
    print(
        f"reaction between steps: p50 {r_p50 * 1e3:.1f} ms, p99 {r_p99 * 1e3:.1f} ms, max "
        f"{max(rx.values(), default=0.0) * 1e3:.1f} ms over {len(rx.by_step)} steps (wall); "
        f"on the critical chain: {rx.critical_s * 1e3:.0f} ms over {rx.critical_n} steps, "
        f"{rx.critical_s * scale:.1f} s of cell time"
    )
    real_makespan = s.makespan_s * scale - rx.critical_s * scale + rx.critical_s
    ratio_real = real_makespan / (bound * scale) if bound > 0 else float("inf")
    verdict = "meets" if ratio_real <= REAL_GOAL else "MISSES"
    print(
        f"ratio_real = (makespan*s - R*s + R) / (bound*s): {ratio_real:.4f} "
        f"(goal <= {REAL_GOAL}: {verdict})"
    )
    speedup = float("nan")  # no baseline run: no speed-up to tell
    runs = [("cellctl", sched)]
    if base is not None:
        b = base.summary
        runs.append(("one-at-a-time", base))
        print(
            f"makespan, one part at a time: {b.makespan_s:.2f} s  "
            f"({sum(b.parts_made.values())} made)"
        )
        speedup = b.makespan_s / s.makespan_s if s.makespan_s > 0 else 0.0
        verdict = "meets" if speedup >= SPEEDUP_GOAL else "MISSES"
        print(
            f"speed-up over one part at a time: {speedup:.3f}x (goal >= {SPEEDUP_GOAL}: {verdict})"
        )
        ceiling = b.makespan_s / bound
        print(f"  the most any schedule could reach: one-at-a-time / bound = {ceiling:.3f}x")
    for label, run in runs:
        util = ", ".join(f"{m} {run.summary.utilization(m):.1%}" for m in run.summary.busy_s)
        print(f"machines' utilization ({label}): {util}")
    for m in config.mills:
        idle, gaps = mill_idle(sched.steps, m.name)
        top = ", ".join(f"{g * 1e3:.0f}" for g in gaps[:3])
        print(
            f"{m.name} neither loaded, cutting nor unloaded (idle, or holding a cut part "
            f"until the next mill is free) between its first load and last unload: {idle:.3f} s "
            f"({len(gaps)} gaps; longest {top} ms)"
        )
    print(f"{robot} idle between its steps: {robot_wait(sched.steps, robot):.2f} s")
    failed = sum(run.summary.steps_failed for _, run in runs)
    print(
        " / ".join(
            f"{label}: failed steps {run.summary.steps_failed}, alarms "
            f"{run.summary.alarms_raised}, held parts {run.summary.parts_held}"
            for label, run in runs
        )
    )
    for label, run in runs:
        _, text = cut_check(run, part_list)
        print(f"emulated mills' logs ({label}): {text}")
        print(f"Gantt chart ({label}): {run.gantt}")
    print(
        machine_line(
            parts=args.parts,
            made=made,
            errors=failed,
            alarms=s.alarms_raised,
            time_scale=scale,
            makespan_s=s.makespan_s,
            bound_s=bound,
            ratio_physical=ratio_physical,
            utilization=utilization,
            reaction_ms_p50=r_p50 * 1e3,
            reaction_ms_p99=r_p99 * 1e3,
            ratio_real=ratio_real,
            speedup=speedup,
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
