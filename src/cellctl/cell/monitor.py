"""G, monitoring: read what is idle, several times a poll period, and turn faults into alarms.

A fault is to be caught within one poll period, so the monitor reads ``SAMPLES`` times a
period (never more often than every ``MIN_SAMPLE`` s) the PLC's inputs (emergency stop, a
PLC that stopped answering, a pallet overdue or come) and each idle mill's readiness (CTS, no
byte sent), and every ``ROBOT_ROUNDS`` rounds the idle robot's machine status (servo error,
power failure, a silent or closed line: a slow serial exchange):
the last look at a mill is what the scheduler trusts (see
:class:`~cellctl.cell.recovery.Recovery`). A mill that lost readiness while idle, or that was
not ready ``setup_timeout`` after its setup, or whose line fails, is a fault: out of the plan
at once, one alarm. A read that takes longer than ``read_limit`` is a machine not answering:
shown so, and the robot out of the plan, at once; alarmed if the read is still out a poll
period after it was sent (an on-delay: a loaded host can hold one answer past the limit, and
an alarm for each such moment would teach the operator to ignore them). A busy
machine is watched by its own step (the robot's status is read while its cycle runs, a
mill's block has its deadline); a machine in the operator's manual use is left alone. Every
round ends by waking the dispatch loop and telling the listeners. Alarms name the cause
(:mod:`cellctl.cell.causes`).

It sees the controller through :mod:`cellctl.cell.ports` only: the world model, the alarm
sink, the PLC, and the mills' fitness in :class:`~cellctl.cell.recovery.Recovery`.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any, TypeVar

from cellctl.cell.causes import ESTOP, Blamed, Cause, link_cause, read_cause, status_cause
from cellctl.errors import CellctlError, DeviceError, UsageError
from cellctl.kinds import Condition, LastError
from cellctl.kinds.families import CycleAborted, setup_lost

if TYPE_CHECKING:
    from cellctl.cell.config import MachineConfig
    from cellctl.cell.model import MachineView
    from cellctl.cell.ports import AlarmSink, PlcAccess, WorldModel
    from cellctl.cell.recovery import Recovery


T = TypeVar("T")

#: Looks per poll period at the PLC and the idle mills (a Modbus request on the network, a
#: modem line): a fault, or a pallet that came, is seen at most a quarter period after.
SAMPLES = 4
#: The idle robot is looked at every this many rounds: a fault is seen at most half a period
#: (and a read) after it shows, within the period with room to spare. A status look takes
#: some 55 ms of its 4800-baud line: one every round kept the line busy nearly half the time,
#: and was most of a plan's exchanges.
ROBOT_ROUNDS = 2
#: The shortest time between two looks, s (short poll periods in tests stay cheap).
MIN_SAMPLE = 0.05


class _StillOut(Exception):
    """The machine's last read has not ended yet: this round does not ask again."""


class _Late(TimeoutError):
    """The read is out past ``read_limit`` (it goes on: see :meth:`Monitor._bounded`)."""


def _consume(task: asyncio.Future[Any]) -> None:
    """Retrieve a late read's outcome (its failure is told by the next look, or was told
    as an alarm already when it stayed out a whole poll period)."""
    if not task.cancelled():
        task.exception()


class Monitor:
    """The controller's monitoring rounds (see module docstring)."""

    def __init__(
        self, world: WorldModel, alarms: AlarmSink, plc: PlcAccess, recovery: Recovery
    ) -> None:
        self.world = world
        self.alarms = alarms
        self.plc = plc
        self.recovery = recovery
        self.done = asyncio.Event()
        self._reads: dict[str, asyncio.Future[Any]] = {}
        self._since: dict[str, float] = {}  # when each key's last read was sent
        self._late_told: set[str] = set()  # keys whose read still out was alarmed
        self._late: set[str] = set()  # keys whose last read outlasted read_limit
        self._inputs: dict[str, bool] = {}  # the PLC's inputs at the last look
        self._estop_seen: float | None = None  # the last look that found the E-stop pressed
        self._last_seen: tuple[object, ...] = ()
        self._robot_looked = float("-inf")  # when the last look at the idle robot began

    async def _bounded(self, key: str, read: Callable[[], Awaitable[T]]) -> T:
        """``read()`` of an idle machine, awaited at most ``read_limit`` (:class:`_Late` after).

        A status exchange takes tens of milliseconds: one that outlasts the limit is a silent
        machine, told now rather than at the driver's own deadline. The read is not cancelled
        (cut mid-exchange it would leave the line out of step): it ends by itself, and until
        it has, the next rounds raise :class:`_StillOut` instead of asking again.
        """
        pending = self._reads.get(key)
        if pending is not None and not pending.done():
            raise _StillOut
        if key in self._late:
            self._late.discard(key)
            failed = None if pending is None or pending.cancelled() else pending.exception()
            if isinstance(failed, TimeoutError | CellctlError) and key not in self._late_told:
                # A late read that then failed by itself (its driver's deadline came before a
                # poll period was out): its failure is the fault, told now as any read's.
                raise failed
        clock = self.world.clock
        # One waiter, woken by the read's own end or by the limit's timer (wait_for around a
        # shield did the same with four more callbacks a read: a plan's busiest path).
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()

        def wake() -> None:
            if not waiter.done():
                waiter.set_result(None)

        async def reading() -> T:
            try:
                return await read()
            finally:
                wake()  # the read's task is done by the time the waiter's task runs

        future = asyncio.ensure_future(reading())
        self._reads[key] = future
        self._since[key] = clock.now()
        self._late_told.discard(key)  # each read is alarmed at most once if it stays out
        timer = clock.call_at(clock.monotonic() + self.world.options.read_limit, wake)
        try:
            await waiter
        finally:
            timer.cancel()
            if not future.done():
                future.add_done_callback(_consume)
        if not future.done():
            self._late.add(key)
            raise _Late
        return future.result()

    def _alarm_if_out_too_long(self, key: str, label: str, view: MachineView) -> None:
        """Alarm ``key``'s read (``label``: "robot", "PLC") once it has been out a whole poll
        period, and only once; ``view`` shows it."""
        since = self._since.get(key)
        if since is None or key in self._late_told:
            return
        if self.world.clock.now() - since < self.world.options.poll_period:
            return
        self._late_told.add(key)
        cause = self._told(read_cause(key, label, TimeoutError()), key)
        view.show(cause.text, Condition.OFFLINE, LastError(cause.text))
        self.alarms.cause_alarm(cause)

    def _reading(self, key: str) -> bool:
        """True while ``key``'s last read is out."""
        pending = self._reads.get(key)
        return pending is not None and not pending.done()

    @property
    def sample_period(self) -> float:
        """Seconds between two rounds."""
        return max(self.world.options.poll_period / SAMPLES, MIN_SAMPLE)

    @property
    def robot_period(self) -> float:
        """Seconds between two looks at the robot's status (idle, or by its transfer)."""
        return ROBOT_ROUNDS * self.sample_period

    async def run(self) -> None:
        """Rounds until :attr:`done` is set (a round in progress finishes first)."""
        clock = self.world.clock
        while not self.done.is_set():
            started = clock.monotonic()
            await self.round()
            # Rounds start every sample period (a round's own time included), not a period
            # after the last one ended: that bounds how late a fault is seen.
            left = self.sample_period - (clock.monotonic() - started)
            with contextlib.suppress(TimeoutError):
                async with clock.timeout(max(left, 0.0)):
                    await self.done.wait()

    async def round(self) -> None:
        world = self.world
        await self._plc()
        await self._robot()
        for m in world.config.mills:
            if world.mill_busy(m.name) or m.name in world.manual_use:
                continue
            await self._mill(m)
        # Dispatch looks again when this look saw something new (an input, a machine's
        # state, readiness): a look that found the cell as it was changes no decision, and
        # the dispatch loop looks once a poll period anyway. (Waking it on every look made
        # it re-plan four times a poll period for nothing: most of a plan's CPU.)
        seen = self._seen()
        if seen != self._last_seen:
            self._last_seen = seen
            self.alarms.wake()
        self.alarms.touch()

    def _seen(self) -> tuple[object, ...]:
        """What a look found, to tell a look that found something new."""
        world = self.world
        views = [world.plc_view(), *world.machines.values()]
        return (
            tuple(sorted(self._inputs.items())),
            tuple((v.state, v.machine_condition, v.in_service) for v in views),
            tuple(sorted(self.recovery.ready.items())),
            self.recovery.robot_ok,
        )

    async def cause_of(
        self, machine: str, error: BaseException, since: float | None = None
    ) -> Cause | None:
        """What made a step on ``machine`` fail, if not the step itself: the PLC (a
        :class:`Blamed` error; a door that did not move under an emergency stop is the
        stop), the machine's link, an emergency stop pressed since the step began at
        ``since`` (``clock.monotonic()``; or pressed now: actuators stop where they are, so a
        robot waiting for a vise never raises its "cycle done"), or a robot status that says
        the arm cannot move (read now, within ``read_limit``, after a reject)."""
        if isinstance(error, Blamed):
            if error.cause.code == "interlock" and await self._estop():
                return ESTOP
            if self._cleared_since(error.cause, error.since):
                return dataclasses.replace(error.cause, told=True)
            return error.cause
        robot = self.world.robot
        label = "robot" if robot is not None and machine == robot.name else "mill"
        cause = link_cause(machine, label, error)
        if cause is None and (self._estop_seen_since(since) or await self._estop()):
            return ESTOP
        if isinstance(error, CycleAborted):
            return status_cause(machine, error.status)
        if cause is not None or label != "robot" or not isinstance(error, DeviceError):
            return cause
        assert robot is not None
        try:
            status = await self._bounded("robot-cause", robot.machine_status)
        except (_StillOut, TimeoutError, CellctlError):
            return None
        return None if status.ok else status_cause(machine, status)

    def _told(self, cause: Cause, key: str) -> Cause:
        """``cause`` of a failed read, marked told if its alarm was cleared while the read
        was out (sent before the operator acknowledged the fault: the same fault)."""
        if self._cleared_since(cause, self._since.get(key, self.world.clock.now())):
            return dataclasses.replace(cause, told=True)
        return cause

    def _cleared_since(self, cause: Cause, since: float) -> bool:
        """True if an alarm of ``cause`` was cleared after ``since``: the operation that
        failed began before the operator acknowledged the fault (see :attr:`Cause.told`)."""
        return any(
            a.machine == cause.machine
            and a.code == cause.code
            and a.cleared is not None
            and a.cleared >= since
            for a in self.world.journal.alarms()
        )

    def _estop_seen_since(self, since: float | None) -> bool:
        """True if a look since ``since`` (``clock.monotonic()``) found the E-stop pressed."""
        return since is not None and self._estop_seen is not None and self._estop_seen >= since

    async def _estop(self) -> bool:
        """True if the PLC's inputs say emergency stop (read now)."""
        try:
            inputs = await self._bounded("plc-cause", self.plc.read_inputs)
        except (_StillOut, TimeoutError, CellctlError):
            return False
        if inputs.get("estop_ok", True):
            return False
        self._estop_seen = self.world.clock.monotonic()
        return True

    async def _plc(self) -> None:
        view = self.world.plc_view()
        try:
            inputs = await self._bounded("plc", self.plc.read_inputs)
        except _StillOut:
            self._alarm_if_out_too_long("plc", "PLC", view)
            return
        except _Late as e:  # shown now; alarmed above if it stays out
            late = read_cause("plc", "PLC", e).text
            view.show(late, Condition.OFFLINE, LastError(late))
            return
        except (TimeoutError, CellctlError) as e:
            cause = self._told(read_cause("plc", "PLC", e), "plc")
            view.show(cause.text, Condition.OFFLINE, LastError.of(e))
            self.alarms.cause_alarm(cause)
            return
        self._inputs = inputs
        view.show("ok", Condition.IDLE)
        self.alarms.returned("plc", "link")
        if not inputs.get("estop_ok", True):
            self._estop_seen = self.world.clock.monotonic()
            self.alarms.cause_alarm(ESTOP)
            view.show("emergency stop", Condition.ALARM, LastError(ESTOP.text))
        else:
            self.alarms.returned("plc", "estop")
        self.plc.pallet_overdue()

    async def _robot(self) -> None:
        world = self.world
        robot = world.robot
        if robot is None:
            return
        view = world.machines[robot.name]
        if self._reading(robot.name):
            # Every round while a look is out, not every few; and even if a transfer was
            # given the robot meanwhile (it waits behind this look on the line).
            self._alarm_if_out_too_long(robot.name, "robot", view)
            return
        if world.robot_busy() or robot.name in world.manual_use:
            return
        # Every ROBOT_ROUNDS rounds (half a round's slack for the rounds' own jitter): a
        # transfer's own status looks watched it meanwhile.
        now = world.clock.monotonic()
        if now - self._robot_looked < self.robot_period - self.sample_period / 2:
            return
        self._robot_looked = now
        try:
            status = await self._bounded(robot.name, robot.machine_status)
        except _StillOut:
            return  # not reached: a read out is handled above
        except _Late as e:  # out of the plan now; alarmed above if it stays out
            late = read_cause(robot.name, "robot", e).text
            view.show(late, Condition.OFFLINE, LastError(late))
            self.recovery.robot_ok = False
            return
        except (TimeoutError, CellctlError) as e:
            cause = self._told(read_cause(robot.name, "robot", e), robot.name)
            view.show(cause.text, Condition.OFFLINE, LastError.of(e))
            self.recovery.robot_ok = False
            self.alarms.cause_alarm(cause)
            return
        # The robot takes work again once a look finds it well (a transfer then initializes
        # it if the fault cost it its start-up).
        self.recovery.robot_ok = status.ok
        if not status.ok:
            cause = status_cause(robot.name, status)
            self.alarms.cause_alarm(cause)
            view.show(str(status), Condition.ALARM, LastError(cause.text))
            self.alarms.returned(robot.name, "link")
        else:
            # Well, and initialized again (a transfer does it): a failed start-up is behind it.
            started = () if robot.cold else ("initialize",)
            self.alarms.returned(robot.name, "link", "status", *started)
            host = robot.host_status()
            view.show(host.text, host.condition)

    def _idle_alarm(self, name: str, shown: str) -> None:
        """Idle mill ``name`` found in an alarm of its own (``shown``: an ISO control's
        "alarm 086 DR OFF"): the operator's to see to, and down time. One alarm per fault: none
        if one of this mill's is active already (the step that met the fault raised it)."""
        active = self.world.journal.active_alarms()
        if any(a.machine == name and a.returned is None and a.code != "status" for a in active):
            return
        self.alarms.cause_alarm(Cause(name, "status", shown))

    async def _mill(self, m: MachineConfig) -> None:
        recovery = self.recovery
        view = self.world.machines[m.name]
        mill = self.world.mills.get(m.name)
        if mill is None:
            return
        try:
            status = await mill.status()
        except (CellctlError, UsageError) as e:
            view.show(f"error: {e}", Condition.OFFLINE, LastError.of(e))
            if view.in_service:
                cause = read_cause(m.name, "mill", e)
                recovery.fault(m.name, "link", cause.text, count=False, cause=cause)
            return
        awaited = recovery.word_awaited(m.name)
        if awaited is None:
            view.show(status.shown, status.kind_condition)
        else:  # what keeps it out of the plan, beside what it shows
            view.show(f"{status.shown}; {awaited}", Condition.ALARM)
        self.alarms.returned(m.name, "link")
        if status.kind_condition is Condition.ALARM and not mill.running:
            self._idle_alarm(m.name, status.shown)
        else:
            self.alarms.returned(m.name, "status")
        if status.ready:
            # Idle: a block an emergency stop could not halt has ended (its alarm says so).
            self.alarms.returned(m.name, "estop")
        was_ready = recovery.ready.get(m.name, False)
        ready = status.takes_work
        if ready and recovery.fit.get(m.name, False):
            self.alarms.returned(m.name, "readiness")  # ready again: CTS high, its setup kept
        recovery.ready[m.name] = ready and recovery.fit.get(m.name, False)
        if not view.in_service or not recovery.fit.get(m.name, False):
            return
        if was_ready and not ready and status.set_up:
            # Not ready (a Dyna's CTS low) on an idle, set-up mill that is not waiting for its
            # operator: it may have been power-cycled, its setup gone with nothing on the line
            # to show it. Said in the family's words: the cell knows no kind's signals.
            why = f" ({status.waiting_for})" if status.waiting_for else ""
            recovery.setup_in_doubt(m.name, f"lost readiness while idle{why}")
        elif setup_lost(status, running=mill.running):
            # Not set up, nobody setting it up, doing nothing: power-cycled behind the cell's
            # back. Recovery sets it up again (what the machine needs), saying so.
            recovery.fault(
                m.name,
                "readiness",
                f"found not set up ({status.shown}): its setup was lost (power cycled?)",
                count=False,
            )
        elif status.awaiting_operator and mill.initialized:
            now = self.world.clock.monotonic()
            since = recovery.setup_at.get(m.name, now)
            if now - since > mill.setup_timeout:
                recovery.fault(
                    m.name,
                    "readiness",
                    f"not ready {mill.setup_timeout:g} s after its setup"
                    + (f": {status.waiting_for}" if status.waiting_for else ""),
                    count=False,
                )
