"""How fast the cell controller catches a fault, per kind, against a bound stated before the run.

The emulated cell (robot, two mills, PLC; time scale 1000, lines paced) runs batches under a
CellController in this process (:class:`cellctl.testing.rig.CellRig`), with the deadlines
``cellctl emulate cell`` writes -- the ones a user gets, nothing shortened. At random moments
each fault kind the emulators offer is switched on (robot: power-off, servo-error, drop,
silent; a mill: never-ready, no-next, drop, stall; PLC: drop, silent, stuck-door, no-pallet,
estop; link-cut: the emulator closes its end of a mill's or the robot's line).

Matching: a fault is detected by the first alarm on the machine it was injected into (the PLC
for a PLC fault) raised after the injection -- and, for a fault measured from its onset, after
the onset. An alarm on another machine is not a detection. A fault with no such alarm within
its window (four times its bound, at least 10 s) is *missed*: it stays in ``n`` and counts as
+inf in the percentiles (so one miss makes p99 and the ratio inf).

Latency is printed from the injection and from the onset (the moment the fault first acted,
recorded by the emulator: a drop at the next request, a stall when the running block ends, a
stuck door when it is next told to move). The ratio is taken on the column the bound is about:

- a fault the machine announces (status bits, a link closed, a PLC input): one poll period,
  from its onset (for most, the injection itself);
- a silence: one poll period plus the machine's reply deadline (the robot's
  ``reply_timeout``, the PLC's ``timeout``), from the injection;
- a step that cannot finish (a stall, never ready, a setup nobody finishes, a stuck door, a
  pallet that does not come): its step deadline plus one poll period for the look that tells
  it, from the onset. A block's deadline is the longest of the cell's programs (its estimate
  times ``block_margin`` plus ``block_extra``).

Bounds come from cell.toml and the programs, printed before the run. After each fault is
detected it stays on until no new alarm came for two poll periods; then the operator switches
it off, clears the alarms and releases held parts (``cellctl alarm clear``, ``cellctl part
release``) without restarting the controller; once the cell has recovered (nothing active,
nothing held, every machine back in the plan) and no alarm came for two poll periods, the
alarms raised since the injection are counted: one per fault is the goal (``mill:no-next`` is
set up by cutting the mill's line first, so two: the cut's and the setup's; being taken out
of service is told on its own and not counted).

Prints per kind ``kind= n= missed= p50_ms= p99_ms= bound_ms= ratio=`` (then the onset/
injection columns and the alarm counts), then ``faults= missed= p99_ratio_max=``.
Goal: missed=0, every ratio <= 1, one alarm per fault.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import math
import random
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from _common import machine_line, percentile
from cellctl.cell.config import load_cell, transfer_ends
from cellctl.cell.controller import CellController
from cellctl.cell.model import ControllerOptions
from cellctl.cell.scheduler import PartState, next_stop
from cellctl.kinds.dyna2400.driver import Dyna2400Mill, MillConfig
from cellctl.kinds.ibm7545.driver import RobotConfig
from cellctl.protocol.plc import PlcMap
from cellctl.testing.rig import CellRig

TIME_SCALE = 1000.0

#: kind -> (class of bound, measured from "injection" or "onset")
KINDS: dict[str, tuple[str, str]] = {
    "robot:power-off": ("announced", "onset"),
    "robot:servo-error": ("announced", "onset"),
    "robot:drop": ("announced", "onset"),
    "robot:silent": ("silence", "injection"),
    "mill:never-ready": ("block", "onset"),
    "mill:no-next": ("setup", "onset"),
    "mill:drop": ("announced", "onset"),
    "mill:stall": ("block", "onset"),
    "plc:drop": ("announced", "onset"),
    "plc:silent": ("silence", "injection"),
    "plc:stuck-door": ("door", "onset"),
    "plc:no-pallet": ("pallet", "onset"),
    "plc:estop": ("announced", "onset"),
    "link-cut": ("announced", "onset"),
}
#: Alarms a fault of this kind should raise (no-next: the bench's own line cut first).
EXPECTED_ALARMS = {"mill:no-next": 2}


@dataclass
class Bounds:
    """Each kind's bound, s, from the cell's configuration (never from the run)."""

    poll: float
    values: dict[str, float]
    notes: list[str] = field(default_factory=list)

    def of(self, kind: str) -> float:
        cls = KINDS[kind][0]
        if cls == "silence":
            return self.values[f"silence:{kind.partition(':')[0]}"]
        return self.values[cls]


def bounds_for(rig: CellRig, controller: CellController) -> Bounds:
    config = load_cell(rig.directory)
    opts = ControllerOptions.from_config(config)
    robot = RobotConfig(**config.robot.options)
    plc = PlcMap.from_toml(config.plc)
    poll = opts.poll_period
    blocks = []
    setups = []
    for mill_config in config.mills:
        mc = MillConfig.from_options(mill_config.options)
        setups.append(mc.setup_timeout)
        mill = controller.mills[mill_config.name]
        assert isinstance(mill, Dyna2400Mill)  # the example cell's mills
        for part in config.parts.values():
            for step in part.route:
                if step.mill != mill_config.name:
                    continue
                toolpath = mill.check(step.program).toolpath
                assert toolpath is not None
                for seconds in toolpath.block_seconds:
                    blocks.append(seconds * mc.block_margin + mc.block_extra)
    values = {
        "announced": poll,
        "silence:robot": poll + robot.reply_timeout,
        "silence:plc": poll + plc.timeout,
        "block": max(blocks) + poll,
        "setup": max(setups) + poll,
        "door": opts.door_start_timeout + poll,
        "pallet": opts.pallet_timeout + poll,
    }
    notes = [
        f"poll_period_s={poll:g} read_limit_s={opts.read_limit:g} "
        f"robot_reply_timeout_s={robot.reply_timeout:g} plc_timeout_s={plc.timeout:g} "
        f"door_start_timeout_s={opts.door_start_timeout:g} "
        f"pallet_timeout_s={opts.pallet_timeout:g} "
        f"setup_timeout_s={max(setups):g} longest_block_deadline_s={max(blocks):g}",
        "bounds: announced = poll; silence = poll + reply deadline; a step that cannot finish "
        "= its deadline + poll",
    ]
    return Bounds(poll, values, notes)


@dataclass
class Injection:
    """One fault switched on: what to switch off after, where it is, and its onset."""

    faults: list[str]
    onset: Callable[[], float | None]
    machine: str
    at: float


def inject(rig: CellRig, kind: str, mill: str | None, rng: random.Random) -> Injection:
    """Switch ``kind`` on (on ``mill`` for a mill fault, if given)."""
    now = time.time()
    if kind == "link-cut":
        name = rng.choice(["robot", "cnc1", "cnc2"])
        line = rig.cell.servers[name].current_line
        if line is not None:
            line.drop()
        return Injection([], lambda: now if line is not None else None, name, now)
    machine, _, name = kind.partition(":")
    if machine == "mill":
        machine = mill or rng.choice(["cnc1", "cnc2"])
    emulators: dict[str, Any] = {"robot": rig.cell.robot, "plc": rig.cell.plc, **rig.cell.mills}
    emulator = emulators[machine]
    switch = name
    if name == "stuck-door":
        switch = f"stuck-door={rng.choice([1, 2])}"
    fault = f"{machine}:{switch}"
    rig.switch_on(fault)
    if name == "no-next":
        # It matters only in a setup: cut the mill's line, and recovery sets it up again
        # (its vise is empty: chosen so by moment()).
        line = rig.cell.servers[machine].current_line
        if line is not None:
            line.drop()
    return Injection([fault], lambda: emulator.onsets.get(name), machine, now)


async def moment(rig: CellRig, kind: str, rng: random.Random) -> str | None:
    """Wait for a random moment of the batch fit for ``kind``: for no-next a mill with an
    empty vise and no step (returned), for a stall or a mill drop one cutting or about to."""
    await asyncio.sleep(rng.uniform(0.2, 1.2))  # a random moment, not a wait for an event
    if kind not in ("mill:no-next", "mill:stall", "mill:drop"):
        return None
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        controller = rig.controller
        names = ["cnc1", "cnc2"]
        rng.shuffle(names)
        for name in names:
            if controller is None or not controller.recovery.usable(name):
                continue
            stepping = controller.step_task(name) is not None
            if kind == "mill:no-next" and empty(rig, controller, name):
                return name
            if kind != "mill:no-next" and stepping:
                return name
        await asyncio.sleep(0.01)  # the controller's state, not signalled
    return None


def empty(rig: CellRig, controller: CellController, mill: str) -> bool:
    """No part in ``mill``'s vise, none there in the journal, none on its way in or out or to
    go there next, no step on it: recovery will set it up again after a cut (with a part in
    its vise it only waits for readiness, and a setup that never runs would leave no-next
    without an onset)."""
    if rig.physical_part(mill) is not None or controller.step_task(mill) is not None:
        return False
    parts = rig.journal.parts(statuses=["waiting", "active", "held"])
    if any(p.location == mill for p in parts):
        return False
    # Nor a part whose next stop it is: one could be loaded between the cut and the look that
    # finds it, and recovery then keeps the setup (no-next would never act).
    types = controller.config.parts
    if any(
        next_stop(PartState(p.id, p.part_type, p.location, p.route_index, p.status), types) == mill
        for p in parts
    ):
        return False
    transfers = rig.open_steps("transfer")
    if controller.step_task(controller.config.robot.name) is not None and not transfers:
        return False  # a transfer just started: where to is not in the journal yet
    return not any(mill in transfer_ends(s.program) for s in transfers)


def not_acted(rig: CellRig, kind: str, machine: str) -> str:
    """Why a fault never acted, as far as the bench can tell."""
    if kind == "mill:no-next":
        parts = rig.journal.parts(statuses=["waiting", "active", "held"])
        if any(p.location == machine for p in parts):
            return "did not act (a part reached its vise: recovery kept its setup)"
        return "did not act (no setup ran)"
    return "did not act"


def recovered(rig: CellRig, controller: CellController) -> bool:
    """Nothing active, nothing held, every machine answering and back in the plan."""
    if rig.journal.active_alarms() or rig.held_parts():
        return False
    if controller.plc_view().state != "ok" or not controller.recovery.robot_ok:
        return False
    return all(
        view.in_service and (controller.recovery.fit.get(name, True))
        for name, view in controller.machines.items()
    )


async def alarms_quiet(rig: CellRig, span: float, timeout: float = 60.0) -> None:
    """Wait until no alarm has been raised for ``span`` s."""
    loop = asyncio.get_running_loop()
    count, since = len(rig.journal.alarms()), loop.time()

    def quiet() -> bool:
        nonlocal count, since
        now = len(rig.journal.alarms())
        if now != count:
            count, since = now, loop.time()
        return loop.time() - since >= span

    await rig.wait_for(quiet, f"no new alarm for {span:g} s", timeout=timeout)


async def operator(rig: CellRig, controller: CellController, verbose: bool) -> bool:
    """The operator's part: clear alarms, release held parts, until the cell has recovered."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            await rig.operator_resolves()
        except AssertionError as e:  # a command refused (the part moved on meanwhile): again
            if verbose:
                print(f"# operator: {str(e).splitlines()[0]}")
        try:
            await rig.wait_for(
                lambda: recovered(rig, controller) or rig.journal.active_alarms(),
                "recovered",
                timeout=10,
            )
        except AssertionError:
            continue
        if recovered(rig, controller):
            return True
    return False


async def detect(
    rig: CellRig, injection: Injection, kind: str, window: float
) -> tuple[float | None, Any]:
    """(onset, the matching alarm or None) within ``window`` s of the injection. For no-next
    the cut's alarm (before the onset) is cleared at once, as the operator at the panel
    would, so the setup nobody finishes is alarmed on its own."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + window
    from_onset = KINDS[kind][1] == "onset"
    onset = None
    while loop.time() < deadline:
        onset = injection.onset()
        after = injection.at if not from_onset or onset is None else onset
        mine = [
            a
            for a in rig.journal.alarms()
            if a.machine == injection.machine and a.raised >= injection.at
        ]
        if onset is not None or not from_onset:
            hits = [a for a in mine if a.raised >= after]
            if hits:
                return onset, min(hits, key=lambda a: a.raised)
        if kind == "mill:no-next":
            for a in mine:
                if a.state == "active" and (onset is None or a.raised < onset):
                    rig.journal.clear_alarm(a.id, by="bench")
        await asyncio.sleep(0.005)  # the journal, not signalled
    return injection.onset(), None


@dataclass
class Figures:
    from_injection: list[float] = field(default_factory=list)
    from_onset: list[float] = field(default_factory=list)
    missed: int = 0
    not_acted: int = 0
    alarms: list[int] = field(default_factory=list)


def show(controller: CellController, heading: str, count: int = 8) -> None:
    """``heading`` and the controller's last ``count`` events."""
    print(f"# {heading}")
    for event in controller.events[-count:]:
        print(f"#   {event.time % 100:6.2f} {event.text}")


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--count", type=int, default=7, help="injections per kind (at 7 or 10, p99 is the worst)"
    )
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--time-scale", type=float, default=TIME_SCALE)
    parser.add_argument("--verbose", action="store_true", help="show each fault's alarms")
    parser.add_argument("--kinds", help="comma-separated kinds to inject (default: all)")
    args = parser.parse_args()
    # The PLC driver turns every pymodbus failure into a typed error, which the controller
    # alarms; pymodbus's own error log of the same failure (with a dump of the last frames
    # sent) would only repeat it, as `cellctl` itself keeps it quiet (cellctl.ui.common).
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    kinds = args.kinds.split(",") if args.kinds else list(KINDS)
    if unknown := set(kinds) - set(KINDS):
        parser.error(f"unknown kinds {sorted(unknown)}; known: {', '.join(KINDS)}")
    rng = random.Random(args.seed)
    figures = {k: Figures() for k in kinds}
    plan = [k for k in kinds for _ in range(args.count)]
    rng.shuffle(plan)
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        rig = CellRig(Path(tmp) / "cell", time_scale=args.time_scale, deadlines="emulated")
        async with rig:
            controller = await rig.start_controller()
            bounds = bounds_for(rig, controller)
            print(f"# time_scale={args.time_scale:g}; deadlines as `cellctl emulate cell` writes")
            for note in bounds.notes:
                print(f"# {note}")
            for kind in kinds:
                cls, base = KINDS[kind]
                print(f"# bound {kind}: {bounds.of(kind) * 1e3:.0f} ms ({cls}, from {base})")
            quiet = 2 * bounds.poll
            orders = 0
            for kind in plan:
                fig = figures[kind]
                if len(rig.journal.parts(statuses=["waiting", "active"])) < 3:
                    orders += 1
                    rig.post("wax-robot-base", 2, f"B{orders}")
                mill = await moment(rig, kind, rng)
                if kind == "plc:no-pallet" or len(rig.journal.parts(statuses=["waiting"])) < 2:
                    orders += 1  # work for every machine, and a pallet to ask for
                    rig.post("wax-robot-base", 2, f"B{orders}")
                before = {a.id for a in rig.journal.alarms()}
                bound = bounds.of(kind)
                window = max(10.0, 4 * bound)
                injection = inject(rig, kind, mill, rng)
                onset, alarm = await detect(rig, injection, kind, window)
                if alarm is None:
                    fig.missed += 1
                    fig.not_acted += onset is None
                    fig.from_injection.append(math.inf)
                    fig.from_onset.append(math.inf)
                    what = (
                        not_acted(rig, kind, injection.machine)
                        if onset is None
                        else "acted, no alarm on its machine"
                    )
                    show(controller, f"{kind} on {injection.machine}: {what} in {window:g} s")
                else:
                    fig.from_injection.append(alarm.raised - injection.at)
                    fig.from_onset.append(alarm.raised - (onset or injection.at))
                    await alarms_quiet(rig, quiet)
                for fault in injection.faults:
                    await rig.switch_off(fault)
                if not await operator(rig, controller, args.verbose):
                    show(controller, f"after {kind}: the cell did not recover in 60 s")
                await alarms_quiet(rig, quiet)
                raised = [
                    a
                    for a in rig.journal.alarms()
                    if a.id not in before and a.code != "out-of-service"
                ]
                fig.alarms.append(len(raised))
                if args.verbose or len(raised) != EXPECTED_ALARMS.get(kind, 1):
                    texts = "; ".join(f"{a.machine}: {a.text}" for a in raised)
                    late = fig.from_onset[-1] * 1e3
                    print(f"# {kind} on {injection.machine}: {late:.0f} ms, {texts}")
                    if args.verbose:
                        show(controller, "the controller's last events", 20)
                await operator(rig, controller, args.verbose)
                rig.check_running()
            await rig.stop_controller(timeout=60)
    print(f"# run took {time.monotonic() - started:.0f} s")
    ratios = []
    total_missed = 0
    wrong = 0
    for kind in kinds:
        fig = figures[kind]
        cls, base = KINDS[kind]
        used = fig.from_onset if base == "onset" else fig.from_injection
        bound = bounds.of(kind)
        p99 = percentile(used, 99)
        ratio = p99 / bound
        ratios.append(ratio)
        total_missed += fig.missed
        expected = EXPECTED_ALARMS.get(kind, 1)
        off = sum(1 for n in fig.alarms if n != expected)
        wrong += off
        print(
            f"kind={kind} n={len(used)} missed={fig.missed} "
            f"p50_ms={percentile(used, 50) * 1e3:.1f} p99_ms={p99 * 1e3:.1f} "
            f"bound_ms={bound * 1e3:.0f} ratio={ratio:.3f} from={base} "
            f"inj_p50_ms={percentile(fig.from_injection, 50) * 1e3:.1f} "
            f"inj_p99_ms={percentile(fig.from_injection, 99) * 1e3:.1f} "
            f"onset_p50_ms={percentile(fig.from_onset, 50) * 1e3:.1f} "
            f"onset_p99_ms={percentile(fig.from_onset, 99) * 1e3:.1f} "
            f"alarms_per_fault={sum(fig.alarms) / max(len(fig.alarms), 1):.2f}/{expected} "
            f"wrong_alarm_count={off}"
        )
    print(
        machine_line(
            faults=sum(len(figures[k].from_onset) for k in kinds),
            missed=total_missed,
            wrong_alarm_count=wrong,
            p99_ratio_max=max(ratios),
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
