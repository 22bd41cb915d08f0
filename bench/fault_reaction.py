"""How fast the cell controller catches a fault: injection to alarm, for every fault kind.

The emulated cell (robot, two mills, PLC; time scale 300, lines paced) runs batches under a
CellController in this process. At random moments, each fault kind the emulators offer is
switched on (robot: power-off, servo-error, drop, silent; a mill: never-ready, no-next (with
a dropped block, so a setup happens), drop, stall; PLC: drop, silent, stuck-door, no-pallet,
estop; a link cut: the emulator closes its end of a mill's or the robot's line). The time
from the injection to the first alarm in the journal is measured; then the fault is switched
off and the operator clears the alarms and releases held parts (as in tests/test_cell_faults)
without restarting the controller, and the batch goes on.

Prints one line per kind (latency p50/p99/max, alarms per fault, misses: no alarm within the
window), then ``faults= p50_ms= p99_ms= poll_ms= ratio=`` with ratio = p99 / poll period.
Goal: ratio <= 1, p50 <= 200 ms, one alarm per fault.
"""

from __future__ import annotations

import argparse
import asyncio
import random
import sys
import tempfile
import time
from pathlib import Path

# The emulated cell, its controller and the operator of the tests (tests/cell_rig.py).
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tests.cell_rig import CellRig
from tests.test_cell_faults import operator_resolves, switch_off

from _common import machine_line
from cellctl.ui.cell_cli import apply_fault

KINDS = [
    "robot:power-off",
    "robot:servo-error",
    "robot:drop",
    "robot:silent",
    "mill:never-ready",
    "mill:no-next",
    "mill:drop",
    "mill:stall",
    "plc:drop",
    "plc:silent",
    "plc:stuck-door",
    "plc:no-pallet",
    "plc:estop",
    "link-cut",
]
WINDOW_S = 20.0


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


def inject(rig: CellRig, kind: str, rng: random.Random) -> list[str]:
    """Switch ``kind`` on; return the faults to switch off afterwards."""
    if kind == "link-cut":
        name = rng.choice(["robot", "cnc1", "cnc2"])
        line = rig.cell.servers[name].current_line
        if line is not None:
            line.drop()
        return []
    machine, _, name = kind.partition(":")
    if machine == "mill":
        machine = rng.choice(["cnc1", "cnc2"])
    if name == "stuck-door":
        name = f"stuck-door={rng.choice([1, 2])}"
    faults = [f"{machine}:{name}"]
    if name == "no-next":
        faults.append(f"{machine}:drop=3")
    for fault in faults:
        apply_fault(rig.cell, fault)
    return faults


async def settle(rig: CellRig) -> None:
    """The operator's part: clear alarms, release held parts, until nothing needs them."""
    for _ in range(6):
        await operator_resolves(rig)
        await asyncio.sleep(0.5)
        if not rig.journal.active_alarms() and not rig.held_parts():
            return


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--count", type=int, default=20, help="injections per kind")
    parser.add_argument("--poll", type=float, default=0.5, help="poll period, s")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    latencies: dict[str, list[float]] = {k: [] for k in KINDS}
    alarms_per: dict[str, list[int]] = {k: [] for k in KINDS}
    missed: dict[str, int] = dict.fromkeys(KINDS, 0)
    plan = [k for k in KINDS for _ in range(args.count)]
    rng.shuffle(plan)
    with tempfile.TemporaryDirectory() as tmp:
        async with CellRig(Path(tmp) / "cell", cell_options={"poll_period": args.poll}) as rig:
            orders = 0
            controller = await rig.start_controller()
            for kind in plan:
                if rig.all_done() or not rig.mailbox.orders():
                    orders += 1
                    rig.post("wax-robot-base", 2, f"B{orders}")
                await asyncio.sleep(rng.uniform(0.5, 3.0))  # a random moment of the batch
                before = {a.id for a in rig.journal.alarms()}
                t0 = time.time()
                faults = inject(rig, kind, rng)
                deadline = time.monotonic() + WINDOW_S
                first = None
                while time.monotonic() < deadline:
                    new = [a for a in rig.journal.alarms() if a.id not in before]
                    if new:
                        first = min(new, key=lambda a: a.raised)
                        break
                    await asyncio.sleep(0.005)
                if first is None:
                    missed[kind] += 1
                else:
                    latencies[kind].append(max(0.0, first.raised - t0))
                await asyncio.sleep(args.poll * 2)  # let the fault play out
                alarms_per[kind].append(
                    len([a for a in rig.journal.alarms() if a.id not in before])
                )
                for fault in faults:
                    switch_off(rig, fault)
                await settle(rig)
                rig.check_running()
            poll_ms = controller.options.poll_period * 1000
            await rig.stop_controller(timeout=60)
    everything: list[float] = []
    for kind in KINDS:
        values = latencies[kind]
        everything += values
        counts = alarms_per[kind]
        print(
            f"{kind:18s} n={len(values):3d} p50_ms={percentile(values, 0.5) * 1e3:8.1f} "
            f"p99_ms={percentile(values, 0.99) * 1e3:8.1f} "
            f"max_ms={max(values, default=float('nan')) * 1e3:8.1f} "
            f"alarms_per_fault={sum(counts) / max(len(counts), 1):.2f} missed={missed[kind]}"
        )
    p99 = percentile(everything, 0.99) * 1e3
    print(
        machine_line(
            faults=len(plan),
            p50_ms=percentile(everything, 0.5) * 1e3,
            p99_ms=p99,
            poll_ms=poll_ms,
            ratio=p99 / poll_ms,
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
