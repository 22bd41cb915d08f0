"""The robot's steps: a transfer between two places, with the program it runs.

A transfer journals its step, has the robot's kind put the program in a partition (downloaded
again only when it is not there), opens the doors on its way, runs the program and waits for
its "cycle done" output (a door that does not open within ``interlock_timeout`` stops the
cycle and is named). A reject before the arm moved is read, reset and retried ``retries``
times; a failure holds the part (a transfer is never restarted automatically).

The controller owns a :class:`RobotSteps` and starts its :meth:`~RobotSteps.transfer` as the
robot's task; it needs of the controller only the world model, the alarm sink and the PLC
(:mod:`cellctl.cell.ports`), and of the other parts the monitor (a failure's cause) and
recovery (a robot fault keeps it out of the plan)::

    steps = RobotSteps(world=c, alarms=c, plc=c, monitor=c.monitor, recovery=c.recovery)
    task = asyncio.create_task(steps.transfer(t))
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import TYPE_CHECKING

from cellctl.cell.causes import Blamed, Cause, blame, door_cause
from cellctl.cell.config import CONVEYOR, open_vise_name
from cellctl.cell.orderflow import OUT
from cellctl.cell.orders import ReportKind
from cellctl.cell.physics import transfer_durations
from cellctl.cell.shift import cell_time_scale
from cellctl.cell.vises import VISE
from cellctl.errors import CellctlError, DeviceError, SignalTimeout, UsageError

#: Seconds between looks at the robot's "cycle done" output: it tells nothing unasked, and
#: each look is two short reads, so the line itself paces most of the wait. Every ms of it is
#: a ms the mills wait for their next part.
CYCLE_END_POLL_S = 0.002
#: Seconds between reads of the PLC while a door or a vise moves (the PLC pushes nothing).
INTERLOCK_POLL_S = 0.005
#: A cycle's output is left unasked for this share of the least time its program takes (the
#: least of the machines' model and of the cycles the cell ran): another start position or
#: a door already on its way can make a cycle a little shorter than the least seen.
EXPECTED_SHARE = 0.9

if TYPE_CHECKING:
    from cellctl.cell.monitor import Monitor
    from cellctl.cell.ports import AlarmSink, PlcAccess, WorldModel
    from cellctl.cell.recovery import Recovery
    from cellctl.cell.scheduler import Transfer


class RobotSteps:
    """The robot's transfers, and the doors they pass (see module docstring)."""

    def __init__(
        self,
        world: WorldModel,
        alarms: AlarmSink,
        plc: PlcAccess,
        monitor: Monitor,
        recovery: Recovery,
    ) -> None:
        self.world = world
        self.alarms = alarms
        self.plc = plc
        self.monitor = monitor
        self.recovery = recovery
        self._modelled: dict[str, float] | None = None  # each program's cycle, its model's
        self._least: dict[str, float] = {}  # each program's shortest cycle seen, s
        self._close_commanded: dict[int, float] = {}  # when each door closing was told to
        self._least_close: dict[int, float] = {}  # each door's shortest close seen, s

    def expected(self, program: str) -> float:
        """Seconds from its doors' command that a cycle of robot program ``program`` cannot
        end sooner (0: not known): :data:`EXPECTED_SHARE` of the least of its model's time
        and the cycles seen."""
        if self._modelled is None:
            config = self.world.config
            try:
                modelled = transfer_durations(config, time_scale=cell_time_scale(config))
                self._modelled = {name: t.seconds for name, t in modelled.items()}
            except Exception:  # no model (or none that can time these programs): the
                self._modelled = {}  # cycles seen only; a figure must not fail a transfer
        # Only once a cycle was seen: a model may not know how fast these machines run (an
        # emulated cell at a time scale its cell.toml does not name).
        seen = self._least.get(program)
        if seen is None:
            return 0.0
        return EXPECTED_SHARE * min(self._modelled.get(program, seen), seen)

    # -- the robot's steps ------------------------------------------------------------------------

    async def _ensure_program(self, name: str) -> int:
        """Where robot program ``name`` is on the robot: the kind puts it there (a download
        only when it is not there already)."""
        robot = self.world.robot
        assert robot is not None
        program = self.world.config.robot_programs[name]
        view = self.world.machines[robot.name]
        sent = False

        def progress(done: int, total: int, sent_bytes: int) -> None:
            nonlocal sent
            if not sent:
                sent = True
                self.alarms.log(f"robot: downloading {name}")
            if view.report_progress(done, total, "records", "downloading", program=name):
                self.alarms.touch()

        try:
            return await robot.ensure_program(name, program, progress)
        finally:
            view.progress = None

    async def doors(self, places: list[str], open_: bool) -> None:
        """Open or close the doors of ``places`` (the conveyor has none). Each must leave its
        other end position within ``door_start_timeout``: one that does not is stuck
        (SignalTimeout in the PLC's words), told now rather than at the interlock's deadline."""
        plc = self.world.plc
        assert plc is not None
        doors = [self.world.mill_index(p) for p in places if p != CONVEYOR]
        for n in doors:
            if open_:
                self._close_commanded.pop(n, None)
            else:  # the first command counts: a door already closing does not start again
                self._close_commanded.setdefault(n, self.world.clock.monotonic())
            await plc.write(f"door_{n}", open_)
        for n in doors:
            away_from = f"door_closed_{n}" if open_ else f"door_open_{n}"
            inputs = await plc.wait_for(
                away_from,
                False,
                timeout=self.world.options.door_start_timeout,
                poll=INTERLOCK_POLL_S,
            )
            if not open_ and inputs.get(f"door_closed_{n}"):
                # Closed already (closed long ago, not reopened): this close times nothing.
                self._close_commanded.pop(n, None)

    async def door_closed(self, mill: str) -> None:
        """Wait up to ``interlock_timeout`` for the door of mill ``mill`` (commanded closed by
        :meth:`doors`) to be closed (SignalTimeout in the PLC's words after).

        Its input is read every :data:`INTERLOCK_POLL_S` once :data:`EXPECTED_SHARE` of the
        shortest close seen has passed, counted from the close's command as a cycle's least
        time is (a true lower bound whatever the host's latency): a door takes seconds, and
        reading it all the way at the poll's rate would be hundreds of requests a step.
        """
        plc = self.world.plc
        assert plc is not None
        clock = self.world.clock
        index = self.world.mill_index(mill)
        # The close this wait times, consumed by it: only one seen travelling from its
        # command counts (a door found closed already, or a wait that failed, times none).
        commanded = self._close_commanded.pop(index, None)
        least = self._least_close.get(index)
        quiet = 0.0  # a close not timed from its command is read at once
        if commanded is not None and least is not None:
            quiet = max(0.0, EXPECTED_SHARE * least - (clock.monotonic() - commanded))
        await plc.wait_for(
            f"door_closed_{index}",
            True,
            timeout=self.world.options.interlock_timeout,
            poll=INTERLOCK_POLL_S,
            expected=quiet,
        )
        if commanded is not None:
            took = clock.monotonic() - commanded
            self._least_close[index] = took if least is None else min(took, least)

    async def _wait_cycle(self, program: str, commanded: float, timeout: float) -> None:
        """Wait up to ``timeout`` s for the end of the cycle of ``program`` (its doors
        commanded at ``commanded``): SignalTimeout after. The output is read every poll once
        the cycle may have ended; the status (a servo error or a power failure that aborted
        the cycle) from the start, as often as the monitor looks at an idle robot."""
        world = self.world
        assert world.robot is not None
        elapsed = world.clock.monotonic() - commanded
        await world.robot.wait_end(
            world.options.done_output,
            timeout=timeout,
            poll=CYCLE_END_POLL_S,
            watch_every=self.monitor.robot_period,
            expected=max(0.0, self.expected(program) - elapsed),
        )

    async def _doors_opened(self, program: str, places: list[str], commanded: float) -> bool:
        """Watch the cycle of ``program`` until the doors of ``places`` (commanded open at
        ``commanded``) are open; True if the cycle ended meanwhile.

        The robot's program waits for the doors itself: this bounds that wait by
        ``interlock_timeout``, as any door's wait is. A door still short of open then is
        stuck: the cycle is stopped (once freed, the door must not let the arm go on by
        itself while its part is held) and the door blamed in the interlock's words, not at
        the transfer's own deadline. Under the emergency stop no door moves: blamed at once
        (the stop is named as its cause). The doors are read once a look at the robot.
        """
        world = self.world
        plc, robot = world.plc, world.robot
        assert plc is not None and robot is not None
        doors = [world.mill_index(p) for p in places if p != CONVEYOR]
        if not doors:
            return False
        waited = world.options.interlock_timeout
        deadline = commanded + waited
        while True:
            with blame("plc", "PLC"):
                inputs = await plc.read_inputs()
            cause = door_cause(inputs, doors, True, waited)
            if cause is None:
                return False
            left = deadline - world.clock.monotonic()
            if left <= 0 or not inputs.get("estop_ok", True):
                # Best effort: a robot that does not take the stop is the operator's to
                # look at, and the door is the fault either way.
                with contextlib.suppress(CellctlError, OSError):
                    await robot.stop()
                since = world.clock.now() - (world.clock.monotonic() - commanded)
                raise Blamed(cause, SignalTimeout(cause.text), since)
            try:
                await self._wait_cycle(program, commanded, min(self.monitor.robot_period, left))
            except SignalTimeout:
                continue
            return True

    async def _door_not_open(self, places: list[str]) -> Cause | None:
        """After a cycle that did not end: a door of ``places`` the program waited for in
        vain (it left its closed position, so the transfer started, but never opened)."""
        plc = self.world.plc
        assert plc is not None
        try:
            inputs = await plc.read_inputs()
        except (CellctlError, OSError):
            return None  # the PLC's own fault is the monitor's to tell
        doors = [self.world.mill_index(p) for p in places if p != CONVEYOR]
        return door_cause(inputs, doors, True, self.world.options.transfer_timeout)

    async def open_vise(self, mill: str) -> None:
        """Open the vise of ``mill``, emptied by hand, with its ``open_vise_<mill>`` program
        (:mod:`cellctl.cell.vises`): no part, no door, no step in the journal (run again
        after a crash, it does no harm). Done once the vise's input says open and the
        program has ended. A failure that is not the robot's, the emergency stop's or the
        PLC link's is the vise's alarm: the program is not run again until it is cleared."""
        world, alarms = self.world, self.alarms
        robot, plc = world.robot, world.plc
        assert robot is not None and plc is not None
        clock = world.clock
        view = world.machines[robot.name]
        program = open_vise_name(mill)
        view.step = program
        alarms.log(f"robot: {program}: opening {mill}'s vise (its part was taken out)")
        started = clock.monotonic()
        running = False
        try:
            if robot.cold:
                await robot.initialize()
            partition = await self._ensure_program(program)
            commanded = clock.monotonic()
            await robot.start(partition)
            running = True
            # The vise's own input first: the cycle's output may still be high from the
            # cycle before (the program lowers it first, but a look can come sooner).
            with blame("plc", "PLC"):
                await plc.wait_for(
                    f"clamp_closed_{world.mill_index(mill)}",
                    False,
                    timeout=world.options.interlock_timeout,
                    poll=INTERLOCK_POLL_S,
                )
            await self._wait_cycle(program, commanded, world.options.interlock_timeout)
            running = False
        except (CellctlError, OSError) as e:
            if running:
                # Its program still runs: stopped, not left waiting on the robot (best
                # effort: a robot that does not take it is its own fault, told below).
                with contextlib.suppress(CellctlError, OSError):
                    await robot.stop()
            culprit = await self.monitor.cause_of(robot.name, e, since=started)
            if culprit is not None and culprit.code != "interlock":
                alarms.cause_alarm(culprit)
                if culprit.machine == robot.name:
                    self.recovery.robot_ok = False
            else:  # the vise that did not open, or the program that did not end
                alarms.alarm(
                    mill,
                    VISE,
                    f"{mill}'s vise: robot program {program} failed: "
                    f"{culprit.text if culprit is not None else e}; {mill} takes no part "
                    f"until its vise is open (clear this alarm to try again)",
                )
            return
        finally:
            view.busy_s += clock.monotonic() - started  # its time, whether it worked or not
            view.step = ""
            alarms.wake()
        alarms.succeeded(robot.name)

    async def transfer(self, t: Transfer) -> None:
        """Carry part ``t.part_id`` from ``t.source`` to ``t.target`` with program
        ``t.program``: journaled, reported, its failure alarmed by its cause."""
        world, alarms = self.world, self.alarms
        robot = world.robot
        assert robot is not None
        view = world.machines[robot.name]
        part = world.journal.get_part(t.part_id)
        try:
            step = world.journal.begin_step(part.id, "transfer", robot.name, t.program)
        except UsageError as e:  # cancelled or scrapped by the operator meanwhile
            alarms.log(f"part {part.id}: transfer {t.program} not started: {e}")
            return
        view.step = f"{t.program} ({part.id})"
        started = self.world.clock.monotonic()
        places = [t.source, t.target]
        attempt = 0
        commanded = started  # when the doors were commanded for the cycle that runs
        moved = False  # the arm may have moved: a failure from here on holds the part
        try:
            rejected: DeviceError | None = None
            while True:
                try:
                    if rejected is None and robot.cold:
                        await robot.initialize()  # a fault since the last cycle cost it
                    if rejected is not None:
                        # Rejected before the arm moved: the reject was read (the driver
                        # does), now reset; a robot that lost its start-up is initialized.
                        await robot.reset_errors()
                        if robot.needs_initialize(rejected):
                            await robot.initialize()
                    partition = await self._ensure_program(t.program)
                    # The cycle's clock starts with the doors, as its model's does: a cycle
                    # started later cannot end sooner than that.
                    commanded = world.clock.monotonic()
                    with blame("plc", "PLC"):
                        await self.doors(places, True)
                    moved = True
                    await robot.start(partition)
                    break
                except DeviceError as e:
                    moved = False  # rejected: the cycle did not start
                    # The reset and the initialize may be rejected too (power still off):
                    # every attempt counts, so the retries stay bounded.
                    attempt += 1
                    rejected = e
                    # A reject because the arm cannot move (power off, servo error) is
                    # alarmed now, not after the retries.
                    cause = await self.monitor.cause_of(robot.name, e)
                    if cause is not None:
                        alarms.cause_alarm(cause)
                    if attempt > world.options.retries:
                        raise
                    alarms.log(f"robot rejected {t.program}: {e}; reset and retry {attempt}")
            # Reported once the arm is on its way: the journal has had the step since before.
            world.mailbox.post_report(
                ReportKind.STEP_STARTED,
                f"{t.program} {part.id}",
                order_id=part.order_id,
                part_id=part.id,
            )
            if not await self._doors_opened(t.program, places, commanded):
                await self._wait_cycle(t.program, commanded, world.options.transfer_timeout)
            cycle = world.clock.monotonic() - commanded
            self._least[t.program] = min(cycle, self._least.get(t.program, cycle))
            with blame("plc", "PLC"):
                await self.doors(places, False)
        except (CellctlError, OSError, asyncio.CancelledError) as e:
            view.busy_s += self.world.clock.monotonic() - started  # a failed step's too
            view.step = ""
            stopped = isinstance(e, asyncio.CancelledError)
            # One alarm, the cause's: the PLC (its E-stop), the robot's link or status, or
            # the transfer. Asked first: the held part's note names it too.
            culprit: Cause | None = None
            if not stopped:
                try:
                    culprit = await self.monitor.cause_of(robot.name, e, since=started)
                    if culprit is None and moved and isinstance(e, SignalTimeout):
                        culprit = await self._door_not_open(places)
                except asyncio.CancelledError:
                    stopped = True  # the operator's stop came while we asked
            what = f"cut short by {world.cancel_reason}" if stopped else f"failed: {e}"
            if culprit is not None and culprit.code == "estop":
                what = f"cut short by the emergency stop ({e})"
            elif culprit is not None and culprit.code == "interlock":
                what = f"failed: {culprit.text} ({e})"
            reason = f"transfer {t.program} {what}"
            if moved or stopped:
                world.journal.end_step(step.id, "failed", str(e) or what, hold=reason)
                world.mailbox.post_report(
                    ReportKind.STEP_FAILED, reason, order_id=part.order_id, part_id=part.id
                )
                world.mailbox.post_report(
                    ReportKind.PART_HELD, reason, order_id=part.order_id, part_id=part.id
                )
            else:
                # The arm never started: the part is where it was, and waits there.
                reason = f"transfer {t.program} not started: {e}"
                world.journal.end_step(step.id, "failed", str(e) or what)
                world.mailbox.post_report(
                    ReportKind.STEP_FAILED, reason, order_id=part.order_id, part_id=part.id
                )
            alarms.wake()
            if stopped:
                if not isinstance(e, asyncio.CancelledError):
                    raise asyncio.CancelledError from e
                raise
            # A fault of the robot's own keeps it out of the plan until the monitor finds
            # it well; only a failure nothing else explains counts towards fail_limit.
            if culprit is None:
                alarms.failed(robot.name, "transfer", reason)
            else:
                alarms.cause_alarm(culprit)
                if culprit.machine == robot.name:
                    self.recovery.robot_ok = False
            return
        view.busy_s += self.world.clock.monotonic() - started
        view.step = ""
        alarms.succeeded(robot.name)
        if t.source == CONVEYOR:
            self.plc.pallet_taken()
        made = t.target == CONVEYOR
        if made:
            world.journal.end_step(step.id, "finished", location=OUT)
            world.journal.finish_part(part.id)
        else:
            world.journal.end_step(step.id, "finished", location=t.target)
        # ``part_done``: the factory counts the order's parts made as they come out.
        world.mailbox.post_report(
            ReportKind.STEP_FINISHED,
            f"{t.program} {part.id}",
            order_id=part.order_id,
            part_id=part.id,
            data={"part_done": True} if made else {},
        )
        alarms.wake()
