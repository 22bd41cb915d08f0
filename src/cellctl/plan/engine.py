"""The plan engine: the real cell controller, its drivers and the emulators on virtual time.

A plan plays a cell forward: the same :class:`~cellctl.cell.controller.CellController` that
runs the real cell, with its drivers, talking byte for byte to the machines' emulators over
``mem://`` lines (the PLC over an in-process Modbus/TCP pair), on an event loop whose time
jumps to the next timer whenever everything waits (:func:`cellctl.clock.run_virtual`). Each
character still takes its line time, each cut its machining time: only the waiting is
skipped. ::

    from cellctl.plan.engine import FaultWindow, PlanInputs, PlanOrder, simulate

    inputs = PlanInputs(
        cell_dir=Path("cell"),                       # cell.toml, robot/, programs/
        orders=(PlanOrder("A", "wax-robot-base", 20, due=friday_6pm),),
        start=monday_6am, until=monday_6am + 8 * 3600,
        faults=(FaultWindow("cnc2", "down", start=t10, end=t11),),
    )
    run = simulate(inputs, workdir=Path("plan-out"))  # a journal and mailbox in plan-out/
    run.finished                                      # {"A": 1764260712.3} (None: not done)

Times are unix seconds of the plan's wall clock (``start`` is the plan's "now").
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cellctl.cell.config import CONVEYOR, CellConfig, load_cell, mill_names
from cellctl.cell.controller import CellController, ControllerOptions
from cellctl.cell.journal import JOURNAL_FILE, Journal, open_journal
from cellctl.cell.scheduler import POLICIES as SCHEDULER_POLICIES
from cellctl.clock import REAL_CLOCK, current_clock, run_virtual
from cellctl.emulators.cell import EmulatedCell
from cellctl.errors import UsageError
from cellctl.files import read_text
from cellctl.mailbox import DONE, MAILBOX_FILE, Mailbox
from cellctl.mailbox.sqlite import SqliteMailbox
from cellctl.plan.faults import PLC, check_switch
from cellctl.plan.operator import PlanOperator
from cellctl.plan.when import PLAN_POLL_S

#: The mailbox's default order priority (``Mailbox.post_order``).
DEFAULT_PRIORITY = 0

#: The scheduler's policies a plan can try (``PlanInputs.policy``): the cell's scheduler's
#: (:data:`cellctl.cell.scheduler.POLICIES`), "default" being its downstream-first.
POLICIES = ("default", *SCHEDULER_POLICIES)

#: Seconds before the plan's start that the emulated machines are switched on: their
#: operators power them up and select the link mode (the Dyna 2400's takes 5 s) before the
#: controller connects at the start, as before a shift.
POWER_ON_S = 10.0

#: Seconds of plan time between two looks of the plan's own watcher (all orders done?): a
#: plan ends at most this much after its last order, its finish time the order's own.
WATCH_S = 30.0

#: Why a machine out of service when the plan began is out in it.
OUT_AT_START = "out of service when the plan began"
#: Seconds of plan time the controller has to take up a cut in flight on a machine out of
#: service (it is taken out after that cut), and how often that is looked at.
TAKE_UP_S = 120.0
TAKE_UP_LOOK_S = 0.05

#: Seconds of plan time the steps in flight have to finish when an error ends a play early,
#: before they are cancelled (a cut's rest, a transfer's; virtual time: it costs little).
END_S = 3600.0
#: Seconds of plan time a cancelled task has to end, and how many times it is asked.
CANCEL_S = 60.0
CANCEL_TRIES = 5


@dataclass(frozen=True)
class PartAt:
    """Where a part of the running cell is: ``location`` (the conveyor or a mill) with
    ``route_index`` of its route's cuts done; ``done_s``: machine seconds of the cut in
    flight on it at ``location`` already done (the plan's mill starts that cut so far in,
    if its emulator can: ``head_start_s`` in docs/kinds.md); more than 0 for a cut in
    flight (a machine out of service finishes it before it is out)."""

    location: str
    route_index: int = 0
    done_s: float = 0.0


@dataclass(frozen=True)
class PlanOrder:
    """An order to play: ``qty`` parts of ``part_type`` (a part type of the cell's cell.toml).

    ``due``: when it is due (unix seconds), if it has a due time; the plan only reports it.
    ``under_way``: where those of the ``qty`` parts already on their way are (a running
    cell's snapshot); the plan takes each up from there, the others from the conveyor.
    """

    order_id: str
    part_type: str
    qty: int
    priority: int = DEFAULT_PRIORITY
    due: float | None = None
    under_way: tuple[PartAt, ...] = ()


@dataclass(frozen=True)
class FaultWindow:
    """A fault on one machine from ``start`` to ``end`` (unix seconds; None: to the end).

    ``fault="down"``: the machine is out of service over the window, as an operator takes it
    out and puts it back. Any other name is the machine's emulator fault switch (as
    ``cellctl emulate cell --fault MACHINE:NAME[=ARG]`` takes it, ``arg`` its argument),
    switched on at ``start`` and off at ``end``, after which the plan's operator resolves
    what the cell holds: clears the alarms and releases held parts where they physically are.
    """

    machine: str
    fault: str
    start: float
    end: float | None = None
    arg: str | None = None


@dataclass(frozen=True)
class HeldPart:
    """A part the running cell holds for the operator now: it stays where it is, held."""

    order_id: str
    part_type: str
    location: str
    route_index: int = 0


@dataclass(frozen=True)
class PlanInputs:
    """Everything a plan is played from (saved beside its output: a plan is reproducible).

    ``cell_dir``: a cell directory (cell.toml, robot/, programs/), copied, never written;
    ``start``/``until``: the plan's wall-clock window (unix seconds); ``policy``: one of
    :data:`POLICIES`; ``seed``: for anything random in the emulators; ``out_of_service``:
    machines out of service at ``start``; ``held``: parts held at ``start``;
    ``poll_period``: how often the planned controller looks at idle machines (see
    :data:`cellctl.plan.when.PLAN_POLL_S`; 0: as often as the cell itself).
    """

    cell_dir: Path
    orders: tuple[PlanOrder, ...]
    start: float
    until: float
    faults: tuple[FaultWindow, ...] = ()
    policy: str = "default"
    seed: int = 0
    out_of_service: tuple[str, ...] = ()
    held: tuple[HeldPart, ...] = ()
    poll_period: float = PLAN_POLL_S


def planned_poll(inputs: PlanInputs, config: CellConfig) -> float:
    """The poll period a plan of ``inputs`` plays: its own, or the cell's if longer."""
    return max(inputs.poll_period, config.poll_period)


@dataclass
class PlanRun:
    """What :func:`simulate` played.

    ``journal_path``: the run's journal (the same schema as a real cell's: steps, parts,
    alarms, with their virtual wall times); ``ended``: the virtual wall time the run stopped
    (every order done, or ``until``); ``wall_s``: real seconds it took; ``finished``: each
    order's finish time (unix seconds), None if it did not finish by ``ended``.
    """

    inputs: PlanInputs
    workdir: Path
    journal_path: Path
    ended: float
    wall_s: float
    finished: dict[str, float | None] = field(default_factory=dict)
    mailbox_path: Path | None = None
    poll_period: float = 0.0


#: A play's progress: told the machine seconds played from its start.
PlayProgress = Callable[[float], None]
#: Seconds of plan time between two looks at how far a play has gone, and the least real
#: seconds between two tellings (what a terminal shows; a pipe to another process carries).
PROGRESS_S = 60.0
PROGRESS_EVERY_S = 0.25


def simulate(inputs: PlanInputs, workdir: Path, *, progress: PlayProgress | None = None) -> PlanRun:
    """Play ``inputs`` on virtual time in ``workdir`` (made if needed; its cell copy, journal
    and mailbox are written there) and return what happened.

    Synchronous: it runs its own virtual-time event loop (:func:`cellctl.clock.run_virtual`),
    so call it from a thread (``asyncio.to_thread``) inside a running loop. Raises
    :class:`~cellctl.errors.UsageError` for inputs the cell cannot take (an unknown part
    type, machine, fault or policy; ``until`` before ``start``) before anything runs.

    ``progress``: told how far the play has gone (machine seconds from ``start``) every
    :data:`PROGRESS_S` of plan time, at most every :data:`PROGRESS_EVERY_S` real seconds;
    none of the plan's own timing changes (its own timers are as they were).
    """
    check_inputs(inputs)
    workdir.mkdir(parents=True, exist_ok=True)
    cell_dir = workdir / "cell"
    if (cell_dir / JOURNAL_FILE).exists() or (cell_dir / MAILBOX_FILE).exists():
        raise UsageError(f"{cell_dir}: a plan ran there already; give an empty directory")
    started = REAL_CLOCK.monotonic()
    play = _play(inputs, cell_dir, progress)
    ended, finished, poll = run_virtual(play, start=inputs.start - POWER_ON_S)
    return PlanRun(
        inputs=inputs,
        workdir=workdir,
        journal_path=cell_dir / JOURNAL_FILE,
        ended=ended,
        wall_s=REAL_CLOCK.monotonic() - started,
        finished=finished,
        mailbox_path=cell_dir / MAILBOX_FILE,
        poll_period=poll,
    )


def check_inputs(inputs: PlanInputs) -> None:
    """Refuse inputs the cell cannot take, in words (:class:`UsageError`)."""
    toml = inputs.cell_dir / "cell.toml"
    try:
        raw = tomllib.loads(read_text(toml))
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise UsageError(f"{toml}: cannot read it: {e}") from None
    parts = raw.get("parts", {})
    machines = raw.get("machines", {})
    if inputs.policy not in POLICIES:
        raise UsageError(f"no scheduler policy {inputs.policy!r}; known: {', '.join(POLICIES)}")
    if not inputs.until > inputs.start:
        raise UsageError("a plan's end (until) must come after its start")
    seen: set[str] = set()
    for order in inputs.orders:
        if order.part_type not in parts:
            raise UsageError(
                f"order {order.order_id}: no part type {order.part_type!r} in {toml} "
                f"(known: {', '.join(parts)})"
            )
        if order.qty < 1:
            raise UsageError(f"order {order.order_id}: quantity must be 1 or more")
        if order.order_id in seen:
            raise UsageError(f"order {order.order_id} is given twice")
        seen.add(order.order_id)
        if len(order.under_way) > order.qty:
            raise UsageError(
                f"order {order.order_id}: {len(order.under_way)} parts under way, "
                f"more than its quantity {order.qty}"
            )
    for name in inputs.out_of_service:
        if name not in machines:
            raise UsageError(f"out of service: no machine {name!r} in {toml}")
    for held in inputs.held:
        if held.part_type not in parts:
            raise UsageError(f"held part of {held.order_id}: no part type {held.part_type!r}")
    _check_places(inputs, raw.get("cell", {}), parts, machines)
    for fault in inputs.faults:
        if fault.machine != PLC and fault.machine not in machines:
            raise UsageError(f"fault {fault.fault} on {fault.machine!r}: no such machine")
        kind = None if fault.machine == PLC else str(machines[fault.machine].get("kind"))
        check_switch(fault.machine, kind, fault.fault, fault.arg)
        if fault.end is not None and not fault.end > fault.start:
            raise UsageError(f"fault {fault.machine}:{fault.fault}: it must end after it starts")


def _check_places(
    inputs: PlanInputs, cell: dict[str, Any], parts: dict[str, Any], machines: dict[str, Any]
) -> None:
    """Refuse a held or under-way part at no place of the cell, with more cuts done than its
    route has, or in a vise another part is in."""
    placed = [
        (f"held part of {h.order_id}", h.part_type, PartAt(h.location, h.route_index))
        for h in inputs.held
    ]
    placed += [
        (f"part of {o.order_id} under way", o.part_type, at)
        for o in inputs.orders
        for at in o.under_way
    ]
    vises: dict[str, str] = {}
    kinds = {n: m.get("kind") for n, m in machines.items() if isinstance(m, dict)}
    mills = mill_names(cell.get("mills"), kinds)
    for who, part_type, at in placed:
        if at.location != CONVEYOR and at.location not in mills:
            raise UsageError(f"{who}: no place {at.location!r} (the conveyor or a mill)")
        route = parts.get(part_type, {}).get("route", [])
        cuts = len(route)
        if not 0 <= at.route_index <= cuts:
            raise UsageError(
                f"{who}: {at.route_index} cuts done, but its route has {cuts} (0 to {cuts})"
            )
        if at.done_s < 0:
            raise UsageError(f"{who}: {at.done_s:g} s of its cut done: it must be 0 or more")
        cut_here = at.route_index < cuts and route[at.route_index].get("mill") == at.location
        if at.done_s > 0 and not cut_here:
            raise UsageError(
                f"{who}: {at.done_s:g} s of a cut done at {at.location}, which does not cut it next"
            )
        if at.location != CONVEYOR:
            if at.location in vises:
                raise UsageError(f"{who}: {at.location}'s vise holds {vises[at.location]}")
            vises[at.location] = who


# -- the play ---------------------------------------------------------------------------------


async def _play(
    inputs: PlanInputs, cell_dir: Path, progress: PlayProgress | None = None
) -> tuple[float, dict[str, float | None], float]:
    """The play (see :func:`simulate`): when it ended, each order's finish, the poll period
    the controller played."""
    clock = current_clock()
    # Every random draw of the machines (a line's noise) from the plan's seed.
    cell = EmulatedCell(time_scale=1.0, links="mem", template=inputs.cell_dir, seed=inputs.seed)
    await cell.start(cell_dir)
    journal = open_journal(cell_dir, clock=clock, durable=False)
    mailbox = SqliteMailbox(cell_dir / MAILBOX_FILE, clock=clock, durable=False)
    controller: CellController | None = None
    stop = asyncio.Event()
    run: asyncio.Task[None] | None = None
    faults: list[asyncio.Task[None]] = []
    told: list[asyncio.Task[None]] = []
    if progress is not None:
        told.append(asyncio.create_task(_tell(inputs, progress), name="plan-progress"))
    try:
        placed = _post(inputs, journal, mailbox)
        await clock.sleep(max(0.0, inputs.start - clock.now()))
        config = load_cell(cell_dir)
        policy = "downstream-first" if inputs.policy == "default" else inputs.policy
        # The cell's deadlines (a silent machine, a door that does not start) stay its own:
        # only how often it looks changes.
        own = ControllerOptions.from_config(config, policy=policy)
        options = dataclasses.replace(own, poll_period=planned_poll(inputs, config), durable=False)
        controller = CellController(config, journal, mailbox, options=options)
        await controller.connect()
        # In the vises once the mills are set up (a setup runs over an empty vise, as the
        # running cell's did long before): a cut under way takes up so far in.
        for at, part_id in placed:
            cell.place(at.location, part_id, done_s=at.done_s)
        # A machine taken out mid-cut finishes that cut first, as it did in the cell: it is
        # taken out once the controller has taken the cut up again.
        cutting = {at.location for o in inputs.orders for at in o.under_way if at.done_s > 0}
        for name in inputs.out_of_service:
            if name not in cutting:
                await controller.set_service(name, False, OUT_AT_START)
        run = asyncio.create_task(controller.run(stop), name="plan-controller")
        for name in inputs.out_of_service:
            if name in cutting:
                await _out_after_its_cut(controller, name, run)
        operator = PlanOperator(controller, cell, journal, inputs.out_of_service)
        faults = [
            asyncio.create_task(operator.window(f, inputs.until), name=f"plan-fault-{i}")
            for i, f in enumerate(inputs.faults)
        ]
        ended = await _watch(inputs, mailbox, run, faults)
        await _end_windows(faults)
        _raise_failed(faults)
        stop.set()
        # Steps in flight at the end finish (as on SIGINT); what they finish counts only if
        # before ``until`` (the orders' done times say).
        await run
        finished = _finished(inputs, mailbox, inputs.until)
        return ended, finished, options.poll_period
    finally:
        # Whatever ended the play, nothing of it may outlive the journal and mailbox closed
        # below: the fault windows, the controller and its steps end first.
        try:
            await _end_windows([*faults, *told])
            if run is not None and controller is not None:
                await _end_controller(controller, run, stop)
        finally:
            if controller is not None:
                with contextlib.suppress(Exception):
                    await controller.close()
            journal.close()
            mailbox.close()
            await cell.close()


async def _tell(inputs: PlanInputs, progress: PlayProgress) -> None:
    """Tell ``progress`` how far the play has gone (see :func:`simulate`), until cancelled."""
    clock = current_clock()
    last = float("-inf")
    while True:
        await clock.sleep(PROGRESS_S)
        now = REAL_CLOCK.monotonic()
        if now - last >= PROGRESS_EVERY_S:
            last = now
            progress(max(0.0, min(clock.now(), inputs.until) - inputs.start))


async def _out_after_its_cut(
    controller: CellController, name: str, run: asyncio.Task[None]
) -> None:
    """Take machine ``name`` out of service once its cut in flight (taken up where it had
    gone) has begun again, as ``cellctl machine NAME out`` left it: the cut finishes, and
    what the cell does after it (the unload) follows. Out at once if the controller has not
    begun it within :data:`TAKE_UP_S` (a mill it cannot use)."""
    clock = current_clock()
    deadline = clock.now() + TAKE_UP_S
    while controller.step_task(name) is None and clock.now() < deadline and not run.done():
        await clock.sleep(TAKE_UP_LOOK_S)
    await controller.set_service(name, False, OUT_AT_START)


def _raise_failed(faults: Sequence[asyncio.Task[None]]) -> None:
    """Raise the error of a fault window that could not be played (say why)."""
    for task in faults:
        if task.done() and not task.cancelled():
            task.result()


async def _end_windows(faults: Sequence[asyncio.Task[None]]) -> None:
    """End the fault windows still waiting (their errors are :func:`_watch`'s to raise)."""
    await _cancel(faults)


async def _end_controller(
    controller: CellController, run: asyncio.Task[None], stop: asyncio.Event
) -> None:
    """Stop the controller after an error: its steps in flight finish (up to
    :data:`END_S` of plan time), else they and it are cancelled; either way it has ended."""
    stop.set()
    controller.poke()
    await asyncio.wait({run}, timeout=END_S)
    await _cancel([run, *controller.steps_in_flight()])


async def _cancel(tasks: Sequence[asyncio.Task[Any]]) -> None:
    """Cancel ``tasks`` and wait, with a deadline, until they have ended. Asked again if one
    goes on: on 3.11 a cancellation that lands in the step where the task's own
    ``asyncio.timeout`` expires can be taken for that timeout and swallowed, and a task
    looping on such waits would run on for ever (on virtual time, its timers jumping)."""
    pending = {t for t in tasks if not t.done()}
    for _ in range(CANCEL_TRIES):
        if not pending:
            break
        for task in pending:
            task.cancel()
        _, pending = await asyncio.wait(pending, timeout=CANCEL_S)
    for task in tasks:
        if task.done() and not task.cancelled():
            task.exception()  # seen: its error is said by whoever ended the play
    if pending:
        names = ", ".join(sorted(t.get_name() for t in pending))
        raise UsageError(f"the plan could not stop its tasks ({names}) after {CANCEL_TRIES} tries")


def _post(inputs: PlanInputs, journal: Journal, mailbox: Mailbox) -> list[tuple[PartAt, str]]:
    """The plan's orders (their parts under way where they are), and the parts held at its
    start (their own one-part orders): in the mailbox and the journal. Returns the parts at
    mills, for the cell's vises: ``(where, part id)``."""
    placed: list[tuple[PartAt, str]] = []
    for order in inputs.orders:
        posted, _ = mailbox.post_order(
            order.part_type, order.qty, order.priority, order_id=order.order_id
        )
        if not order.under_way:
            continue
        # Taken as the controller takes an order, then its first parts put where the running
        # cell has them: the controller goes on with them as after a restart.
        mailbox.set_order_state(order.order_id, "accepted")
        parts = journal.create_parts(posted)
        for part, at in zip(parts, order.under_way, strict=False):
            journal.move_part(part.id, at.location, at.route_index)
            if at.location != CONVEYOR:
                placed.append((at, part.id))
    for n, held in enumerate(inputs.held, start=1):
        oid = f"{held.order_id}~held{n}"
        posted, _ = mailbox.post_order(held.part_type, 1, order_id=oid)
        mailbox.set_order_state(oid, "accepted")
        (part,) = journal.create_parts(posted)
        journal.move_part(part.id, held.location, held.route_index)
        journal.hold_part(part.id, "held when the plan began")
        if held.location != CONVEYOR:
            placed.append((PartAt(held.location, held.route_index), part.id))
    return placed


async def _watch(
    inputs: PlanInputs,
    mailbox: Mailbox,
    run: asyncio.Task[None],
    faults: Sequence[asyncio.Task[None]] = (),
) -> float:
    """Until every order is done (its time) or ``until`` comes (``until``); raises what ended
    the controller or a fault window early."""
    clock = current_clock()
    ids = [o.order_id for o in inputs.orders]
    left = list(reversed(ids))  # the orders not seen done yet, the first to look at last
    while True:
        if run.done():
            run.result()  # the controller died: say why
            raise UsageError("the cell's controller stopped on its own")
        _raise_failed(faults)
        now = clock.now()
        if now >= inputs.until:
            return inputs.until
        # A done order stays done: each look asks only about those not seen done (one
        # order, mostly), not for every order of a week's plan every look.
        while left and mailbox.get_order(left[-1]).state == DONE:
            left.pop()
        if ids and not left:
            return max(mailbox.get_order(i).updated for i in ids)
        # Woken at once by the controller's or a fault window's end, else a look later.
        running = [run, *(f for f in faults if not f.done())]
        with contextlib.suppress(TimeoutError):
            async with clock.timeout(min(WATCH_S, inputs.until - now)):
                await asyncio.wait(running, return_when=asyncio.FIRST_COMPLETED)


def _finished(inputs: PlanInputs, mailbox: Mailbox, until: float) -> dict[str, float | None]:
    states = {o.id: o for o in mailbox.orders()}
    out: dict[str, float | None] = {}
    for order in inputs.orders:
        state = states[order.order_id]
        done = state.state == DONE and state.updated <= until
        out[order.order_id] = state.updated if done else None
    return out


__all__ = [
    "DEFAULT_PRIORITY",
    "POLICIES",
    "FaultWindow",
    "HeldPart",
    "PartAt",
    "PlanInputs",
    "PlanOrder",
    "PlanRun",
    "check_inputs",
    "simulate",
]
