"""How fast the cell controller catches a fault: onset to alarm, for every fault kind.

The emulated cell (robot, two mills, PLC; time scale 1000, lines paced) runs batches under a
CellController in this process. At random moments, each fault kind the emulators offer is
switched on (robot: power-off, servo-error, drop, silent; a mill: never-ready, no-next (with
a dropped block, so a setup happens), drop, stall; PLC: drop, silent, stuck-door, no-pallet,
estop; a link cut: the emulator closes its end of a mill's or the robot's line).

A fault switched on may act only later (a drop at the next request or block, a stall when
the running block ends, a stuck door when it is next told to move): the emulators record that
onset (``emulator.onsets``), and the latency is measured from it to the first alarm in the
journal. A fault that did not act within the window is counted as ``not_shown``; one that
acted and raised no alarm within the window as ``missed``. Then the fault is switched off and
the operator clears the alarms and releases held parts (as in tests/test_cell_faults)
without restarting the controller, and the batch goes on.

Faults seen as something *not* happening are told at their allowance, set here as a user of
a cell this fast would (stated in the first line printed): ``read_limit`` and the robot's
``reply_timeout`` (silent), ``pallet_timeout`` (no pallet), a mill's ``setup_timeout``
(no NEXT) and ``block_extra`` (a block that does not end). The rest are told at the next
look (the monitor looks four times a poll period) or by the step that meets them.

Prints one line per kind (latency p50/p99/max, alarms per fault, misses), then
``faults= p50_ms= p99_ms= poll_ms= ratio=`` with ratio = p99 / poll period.
Goal: ratio <= 1, p50 <= 200 ms, one alarm per fault.
"""

from __future__ import annotations

import argparse
import asyncio
import random
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# The emulated cell, its controller and the operator of the tests (tests/cell_rig.py).
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tests.cell_rig import TIME_SCALE, CellRig
from tests.test_cell_faults import operator_resolves, switch_off

from _common import machine_line
from cellctl.cell.controller import CellController
from cellctl.cell.journal import Alarm
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
#: Allowance for a fault seen as something not happening, s: at time scale 1000 the
#: conveyor takes 8 ms, a setup 20 ms, a door 2 ms, so this is ten times each and more.
ALLOWANCE_S = 0.2
#: A block running this many times its estimated time is stalled.
BLOCK_MARGIN = 1.3


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


@dataclass
class Injection:
    """One fault switched on: what to switch off after, and where its onset shows."""

    faults: list[str]
    onset: Callable[[], float | None]
    machine: str  # the machine it is on (a mill's setup alarm after a drop is its own)


def inject(rig: CellRig, kind: str, rng: random.Random) -> Injection:
    """Switch ``kind`` on."""
    if kind == "link-cut":
        name = rng.choice(["robot", "cnc1", "cnc2"])
        line = rig.cell.servers[name].current_line
        now = time.time()
        if line is not None:
            line.drop()
        return Injection([], lambda: now if line is not None else None, name)
    machine, _, name = kind.partition(":")
    if machine == "mill":
        machine = rng.choice(["cnc1", "cnc2"])
    emulators: dict[str, Any] = {"robot": rig.cell.robot, "plc": rig.cell.plc, **rig.cell.mills}
    emulator = emulators[machine]
    switch = name
    if name == "stuck-door":
        switch = f"stuck-door={rng.choice([1, 2])}"
    faults = [f"{machine}:{switch}"]
    for fault in faults:
        apply_fault(rig.cell, fault)
    if name == "no-next":
        # It matters only in a setup: cut the mill's line, and recovery sets it up again
        # (with its vise empty; a part in it keeps the setup).
        line = rig.cell.servers[machine].current_line
        if line is not None:
            line.drop()
    return Injection(faults, lambda: emulator.onsets.get(name), machine)


async def moment(rig: CellRig, kind: str, rng: random.Random) -> str | None:
    """Wait for a random moment of the batch fit for ``kind``; for no-next, one with an
    empty vise and no step on the mill (returned; None if none came)."""
    await asyncio.sleep(rng.uniform(0.5, 3.0))
    if kind != "mill:no-next":
        return None
    deadline = time.monotonic() + WINDOW_S
    while time.monotonic() < deadline:
        for name, n in (("cnc1", 1), ("cnc2", 2)):
            controller = rig.controller
            if (
                controller is not None
                and rig.cell.vise[n] is None
                and controller.step_task(name) is None
                and controller.recovery.usable(name)
            ):
                return name
        await asyncio.sleep(0.01)
    return None


async def settle(rig: CellRig) -> None:
    """The operator's part: clear alarms, release held parts, until nothing needs them."""
    for _ in range(6):
        try:
            await operator_resolves(rig)
        except AssertionError as e:  # a command refused (the part moved on meanwhile): again
            print(f"# operator: {e}".splitlines()[0])
        await asyncio.sleep(0.5)
        if not rig.journal.active_alarms() and not rig.held_parts():
            return


def show(controller: CellController, heading: str) -> None:
    """``heading`` and the controller's last events (``--verbose``)."""
    print(f"# {heading}")
    for event in controller.events[-8:]:
        print(f"#   {event.text}")


async def plc_answers(controller: CellController, previous: str) -> None:
    """Wait until the controller reads the PLC again (a silent PLC's late answers drain
    first); say so if it does not, since the next fault's alarm would be the PLC's."""
    deadline = time.monotonic() + 10
    while controller.plc_view().state != "ok" and time.monotonic() < deadline:  # noqa: ASYNC110 - the monitor's look, not signalled
        await asyncio.sleep(0.05)
    if controller.plc_view().state != "ok":
        print(f"# PLC still {controller.plc_view().state!r} 10 s after {previous}")


async def first_alarm(rig: CellRig, before: set[int], kind: str, onset: float) -> Alarm | None:
    """The first alarm raised at or after ``onset`` (None after the window). For no-next the
    dropped block's alarm comes first: cleared at once, as an operator at the panel would,
    so the setup that nobody finishes is alarmed on its own."""
    deadline = time.monotonic() + WINDOW_S
    while time.monotonic() < deadline:
        new = [a for a in rig.journal.alarms() if a.id not in before]
        after = [a for a in new if a.raised >= onset - 0.005]
        if after:
            return min(after, key=lambda a: a.raised)
        if kind == "mill:no-next":
            for a in new:
                if a.state == "active" and a.raised < onset:
                    rig.journal.clear_alarm(a.id, by="bench")
        await asyncio.sleep(0.005)
    return None


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--count", type=int, default=20, help="injections per kind")
    parser.add_argument("--poll", type=float, default=0.5, help="poll period, s")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--verbose", action="store_true", help="show each fault's alarms")
    parser.add_argument("--kinds", help="comma-separated kinds to inject (default: all)")
    args = parser.parse_args()
    kinds = args.kinds.split(",") if args.kinds else KINDS
    if unknown := set(kinds) - set(KINDS):
        parser.error(f"unknown kinds {sorted(unknown)}; known: {', '.join(KINDS)}")
    rng = random.Random(args.seed)
    latencies: dict[str, list[float]] = {k: [] for k in KINDS}
    alarms_per: dict[str, list[int]] = {k: [] for k in KINDS}
    missed: dict[str, int] = dict.fromkeys(KINDS, 0)
    not_shown: dict[str, int] = dict.fromkeys(KINDS, 0)
    plan = [k for k in kinds for _ in range(args.count)]
    rng.shuffle(plan)
    limit = args.poll / 2
    cell_options = {
        "poll_period": args.poll,
        "read_limit": limit,
        "pallet_timeout": ALLOWANCE_S,
        "interlock_timeout": ALLOWANCE_S,
    }
    mill_options = {
        "setup_timeout": ALLOWANCE_S,
        "block_extra": ALLOWANCE_S / 2,  # on top of the margin below
        "ready_wait": ALLOWANCE_S,
        # A block may run 1.3 times its estimate (in the real cell's time, hence the scale):
        # the emulated mill's blocks take about 1.2 times the toolpath's estimate.
        "block_margin": BLOCK_MARGIN / TIME_SCALE,
    }
    print(
        f"# poll_s={args.poll:g} read_limit_s={limit:g} reply_timeout_s={limit:g} "
        f"allowance_s={ALLOWANCE_S:g} (pallet, setup, ready_wait, interlock) "
        f"block_margin={BLOCK_MARGIN:g} block_extra_s={ALLOWANCE_S / 2:g}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        rig = CellRig(Path(tmp) / "cell", cell_options=cell_options, mill_options=mill_options)
        async with rig:
            toml = rig.directory / "cell.toml"
            toml.write_text(
                toml.read_text() + f"\n[machines.robot.options]\nreply_timeout = {limit:g}\n"
            )
            orders = 0
            controller = await rig.start_controller()
            for kind in plan:
                open_parts = rig.journal.parts(statuses=["waiting", "active"])
                if len(open_parts) < 3:
                    orders += 1
                    rig.post("wax-robot-base", 2, f"B{orders}")
                mill = await moment(rig, kind, rng)
                if kind == "plc:no-pallet" or len(rig.journal.parts(statuses=["waiting"])) < 2:
                    # Work for every machine, and a pallet to ask for.
                    orders += 1
                    rig.post("wax-robot-base", 2, f"B{orders}")
                before = {a.id for a in rig.journal.alarms()}
                injection = inject(rig, kind if mill is None else f"{mill}:no-next", rng)
                onset = None
                deadline = time.monotonic() + WINDOW_S
                while onset is None and time.monotonic() < deadline:
                    onset = injection.onset()
                    await asyncio.sleep(0.005)
                if onset is None:
                    not_shown[kind] += 1
                    if args.verbose:
                        show(controller, f"{kind}: did not act within {WINDOW_S:g} s")
                else:
                    first = await first_alarm(rig, before, kind, onset)
                    if first is None:
                        missed[kind] += 1
                        if args.verbose:
                            show(controller, f"{kind}: acted, no alarm within {WINDOW_S:g} s")
                    else:
                        latencies[kind].append(max(0.0, first.raised - onset))
                        await asyncio.sleep(args.poll * 2)  # let the fault play out
                        raised = [
                            a
                            for a in rig.journal.alarms()
                            if a.id not in before and a.raised >= onset - 0.005
                        ]
                        alarms_per[kind].append(len(raised))
                        if args.verbose:
                            texts = "; ".join(f"{a.machine}: {a.text}" for a in raised)
                            late = (first.raised - onset) * 1e3
                            print(f"# {kind}: {late:.0f} ms, {len(raised)} alarms: {texts}")
                for fault in injection.faults:
                    switch_off(rig, fault)
                await settle(rig)
                rig.check_running()
                await plc_answers(controller, kind)
            poll_ms = controller.options.poll_period * 1000
            await rig.stop_controller(timeout=60)
    everything: list[float] = []
    for kind in kinds:
        values = latencies[kind]
        everything += values
        counts = alarms_per[kind]
        print(
            f"{kind:18s} n={len(values):3d} p50_ms={percentile(values, 0.5) * 1e3:8.1f} "
            f"p99_ms={percentile(values, 0.99) * 1e3:8.1f} "
            f"max_ms={max(values, default=float('nan')) * 1e3:8.1f} "
            f"alarms_per_fault={sum(counts) / max(len(counts), 1):.2f} "
            f"missed={missed[kind]} not_shown={not_shown[kind]}"
        )
    p99 = percentile(everything, 0.99) * 1e3
    print(
        machine_line(
            faults=len(everything),
            p50_ms=percentile(everything, 0.5) * 1e3,
            p99_ms=p99,
            poll_ms=poll_ms,
            ratio=p99 / poll_ms,
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
