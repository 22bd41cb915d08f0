"""Recovery: which machines may take work, and bringing back the ones that may not.

A mill may take work (:meth:`Recovery.usable`) only when its setup succeeded since its last
initialization or fault (*fit*) and the last poll saw it ready (CTS high, state 2). A failed
setup, a lost readiness, a stall or a failed step makes it unfit at once, with one alarm in
the machine's words (:meth:`Recovery.fault`); the scheduler then plans without it, and a
recovery task per machine brings it back: reopen its link if it closed, initialize it again
with force (the documented way out of a stuck state), every poll period until that succeeds
or the machine is out of service (``fail_limit`` failures in a row). The next poll that sees
it ready puts it back in the plan. A link is reopened by one caller at a time (the dispatch
loop's round or the mill's recovery), at once when it is found closed, then after a pause that
doubles from one poll period up to :data:`REOPEN_WAIT_MAX` until the machine is well again: a
device server that refuses for a moment after a drop (ser2net's "Port already in use", or a
connection it takes and closes at once) is not asked again every round.

A mill that left ready while idle (:meth:`Recovery.setup_in_doubt`) may have been power-cycled:
its setup (a zero only its operator sets) can be gone with nothing on the line to show it. The
cell trusts that setup no more: it sets the mill up again itself when it can (a setup program,
no part in the vise, none on its way there), and otherwise waits for the operator's word (the
fault's alarm acknowledged, or the mill returned to service) before it takes work again.

The controller owns this object and calls it; it needs of the controller only the world model
(machines, drivers, options), the alarm sink and a way to reopen a link
(:mod:`cellctl.cell.ports`).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING

from cellctl.cell.causes import LINK_CLOSED, Cause
from cellctl.cell.config import transfer_ends
from cellctl.errors import CellctlError
from cellctl.kinds import Condition, LastError
from cellctl.kinds.families import setup_lost
from cellctl.tasks import cancel_and_wait

if TYPE_CHECKING:
    from cellctl.cell.config import MachineConfig
    from cellctl.cell.ports import AlarmSink, LinkOpener, WorldModel

#: What names a failure by its cause, from the machine and the error (the monitor's
#: :meth:`~cellctl.cell.monitor.Monitor.cause_of`); None: only the failure explains it.
CauseFinder = Callable[[str, BaseException], Awaitable[Cause | None]]

#: The longest pause between two attempts to reopen a machine's link, s (the pause doubles
#: from one poll period up to this).
REOPEN_WAIT_MAX = 5.0


class SetupLost(CellctlError):
    """A mill found not set up, that the cell cannot set up (it has no setup program)."""


class Recovery:
    """Fitness of every mill, and the tasks that bring unfit machines back."""

    def __init__(self, world: WorldModel, alarms: AlarmSink, links: LinkOpener) -> None:
        self.world = world
        self.alarms = alarms
        self.links = links
        self.fit: dict[str, bool] = {m.name: False for m in world.config.mills}
        self.ready: dict[str, bool] = {m.name: False for m in world.config.mills}
        self.setup_at: dict[str, float] = {}
        self.faulted: set[str] = set()
        self.robot_ok = True
        """False from a robot fault (its status, its link) until the monitor's next good look."""
        self._tasks: dict[str, asyncio.Task[None]] = {}
        self._halted: set[str] = set()  # mills an emergency stop sent END, until resume
        self._resumed: set[str] = set()  # halted mills the resume sets up, part or no part
        # Mills whose setup is in doubt: when the doubt began, and the alarm whose
        # acknowledgement is the operator's word that the setup is kept.
        self._doubted: dict[str, tuple[float, int | None]] = {}
        # Mills whose cut failed on a door or vise the PLC did not move: no cut until the
        # operator clears the PLC's interlock alarm.
        self._interlocked: set[str] = set()
        # Mills whose step failed on the machine's own word while its block ran on (past its
        # deadline: a stall), until set up again: a block still running then is the fault.
        self._overran: set[str] = set()
        # Reopens of a link, one at a time per machine: the dispatch loop's round and the
        # mill's recovery both reopen, and a second open while the first is under way would
        # be refused by the machine's owner lock (a failure the backoff would then count).
        self._reopening: dict[str, asyncio.Lock] = {}
        # Machines whose link was found closed since they were last well: when the next
        # attempt to reopen it may be made, and the pause after that one.
        self._reopen_at: dict[str, tuple[float, float]] = {}

    # -- what the scheduler asks ----------------------------------------------------------------

    def usable(self, name: str) -> bool:
        """True if mill ``name`` may be given work now (a link seen closed is a fault not
        yet handled: no part goes into a mill recovery may have to set up again)."""
        mill = self.world.mills.get(name)
        if mill is None or mill.link.closed or self._interlock_alarm(name) is not None:
            return False
        return self.fit.get(name, False) and self.ready.get(name, False)

    def interlocked(self, name: str) -> None:
        """Mill ``name``'s cut failed on a door or vise that did not move: it takes no work
        until the operator clears the PLC's interlock alarm (see :meth:`robot_may_move`)."""
        self._interlocked.add(name)

    def _interlock_alarm(self, name: str) -> int | None:
        """The interlock alarm mill ``name`` waits to see cleared, if it waits for one."""
        if name not in self._interlocked:
            return None
        alarm = self.world.journal.open_alarm("plc", "interlock")
        if alarm is None:
            self._interlocked.discard(name)  # cleared: its door or vise was seen to
            return None
        return alarm.id

    def unusable(self) -> set[str]:
        return {name for name in self.fit if not self.usable(name)}

    def robot_may_move(self) -> bool:
        """True if the robot may start a transfer: no fault of its own since the monitor's
        last good look (:attr:`robot_ok`), and no door or vise the PLC failed to move still
        alarmed. A stuck door is a physical fault: transfers wait for the operator's clear
        rather than fail through it again at once (each retry a failed step, round after
        round)."""
        if not self.robot_ok:
            return False
        return self.world.journal.open_alarm("plc", "interlock") is None

    # -- faults -------------------------------------------------------------------------------

    def fault(
        self, name: str, code: str, text: str, *, count: bool = True, cause: Cause | None = None
    ) -> None:
        """Mill ``name`` cannot take work: out of the plan at once, one alarm, recovery.

        The alarm is ``cause``'s when one is given (its link, the PLC), else ``code`` and
        ``text``. A fault another machine caused does not count towards this one's
        ``fail_limit``. Further faults while it recovers (the forced setup failing again)
        raise no new alarm while its alarm is active: they only count. Once the operator
        cleared it, a mill that still fails (a setup nobody finishes) says so again.
        """
        blamed = cause.machine if cause is not None else name
        alarm = name not in self.faulted or not any(
            a.machine in (name, blamed) for a in self.world.journal.active_alarms()
        )
        self.faulted.add(name)
        self.fit[name] = False
        self.ready[name] = False
        if alarm:
            self.alarms.cause_alarm(cause or Cause(name, code, text))
        if count and (cause is None or cause.machine == name):
            self.alarms.failed(name, code, text, alarm=False)
        self._start(name)

    def setup_in_doubt(self, name: str, what: str) -> None:
        """Mill ``name`` was seen to leave ready while idle (``what``, in the machine's
        words): a fault, and its setup trusted no more (see module docstring)."""
        now = self.world.clock.now()
        config = self.world.config.machine(name)
        if config.setup is not None and not self._occupied(name):
            text = f"{what}: its setup is in doubt (power cycled?): it is set up again once ready"
        else:
            # A part on its way in is the vise's state by the time the mill is ready again:
            # decided now, the alarm must not promise a setup that cannot run over it.
            if config.setup is None:
                why = "it has no setup program"
            elif self._loading(name):
                why = "a part is being loaded into its vise"
            else:
                why = "a part is in its vise"
            text = (
                f"{what}: its setup is in doubt (power cycled?) and {why}: check its setup at "
                "the machine, then acknowledge this alarm"
            )
        self.fault(name, "readiness", text, count=False)
        alarm = next((a for a in self.world.journal.active_alarms() if a.machine == name), None)
        self._doubted[name] = (now, None if alarm is None else alarm.id)

    def word_awaited(self, name: str) -> str | None:
        """What mill ``name`` waits for from its operator before it takes work (a door or
        vise that did not move, its setup in doubt), to show beside its status; None:
        nothing."""
        stuck = self._interlock_alarm(name)
        if stuck is not None:
            return f"its door or vise did not move: clear alarm {stuck} once freed"
        awaited = self._word_awaited(name)
        if awaited is None:
            return None
        return f"its setup in doubt: acknowledge alarm {awaited} once checked"

    def _word_awaited(self, name: str) -> int | None:
        """The alarm whose acknowledgement mill ``name`` waits for (its setup in doubt), or
        None if it waits for none: no doubt, or the operator has acknowledged or cleared it
        since the doubt began."""
        since, alarm_id = self._doubted.get(name, (0.0, None))
        if alarm_id is None:
            return None
        alarm = self.world.journal.get_alarm(alarm_id)
        if alarm.state == "cleared" or (alarm.acked is not None and alarm.acked >= since):
            return None
        return alarm_id

    def halted(self, name: str) -> None:
        """Mill ``name`` was sent END by an emergency stop: out of the plan (no alarm of its
        own: the stop has one) until :meth:`resume_halted` initializes it again."""
        self.fit[name] = self.ready[name] = False
        self._halted.add(name)

    def resume_halted(self) -> None:
        """The cell resumes: recovery initializes every halted mill anew (its operator readied
        it at its panel meanwhile; if not, the setup's refusal is its alarm, as for any fault).
        Not before: no setup moves a mill while the operator deals with an emergency stop."""
        for name in sorted(self._halted):
            # Its setup runs even over a part in its vise (released to be cut again): END
            # took the setup, and without one it never shows ready (the operator resumed).
            self._resumed.add(name)
            self._start(name)
        self._halted.clear()

    def _start(self, name: str) -> None:
        task = self._tasks.get(name)
        if task is None or task.done():
            self._tasks[name] = asyncio.create_task(self._recover(name))

    async def _recover(self, name: str) -> None:
        world = self.world
        config = world.config.machine(name)
        while not self.fit[name] and not world.stopping:
            await world.clock.sleep(world.options.poll_period)
            view = world.machines[name]
            if not view.in_service or name in world.manual_use or world.step_task(name):
                continue
            if not await self.reopen_mill(config):
                continue
            doubt_left = name in self._doubted and config.setup is None
            if (self._occupied(name) or doubt_left) and name not in self._resumed:
                await self._await_readiness(config)
            else:
                await self.prepare_mill(config, force=True)
        self._resumed.discard(name)

    def overran(self, name: str) -> None:
        """Mill ``name``'s step failed on the machine's own word while its block ran on (its
        deadline passed): a block still running after it is a fault (see _still_running),
        not one that ends by itself (a step cut by its link)."""
        self._overran.add(name)

    def _still_running(self, name: str) -> None:
        """Mill ``name``'s block runs on after its step failed (a stall: it never said READY
        again): the operator's to stop at the machine. Alarmed again once its alarm is
        cleared while it still runs, as any fault still there is (else the cell would wait
        on it unsaid)."""
        active = self.world.journal.active_alarms()
        if any(a.machine == name and a.returned is None for a in active):
            return
        text = "its block still runs after its step failed: stop it at the machine"
        self.alarms.cause_alarm(Cause(name, "machining", text))
        self.world.machines[name].show(f"executing (left running): {text}", Condition.ALARM)

    def _occupied(self, name: str) -> bool:
        """A part is in the mill's vise, or on its way there: its setup program does not run
        over it (nor while the arm puts a part into the vise)."""
        parts = self.world.journal.parts(statuses=["waiting", "active", "held"])
        return any(p.location == name for p in parts) or self._loading(name)

    def _loading(self, name: str) -> bool:
        """A transfer into mill ``name`` is under way (its part is in the vise once it ends)."""
        return any(
            s.kind == "transfer" and transfer_ends(s.program)[1] == name
            for s in self.world.journal.open_steps()
        )

    async def _await_readiness(self, m: MachineConfig) -> None:
        """With a part in the vise (or no setup program): back in the plan once it shows
        ready with its setup kept (state 2, CTS high) and, if its setup is in doubt, on the
        operator's word; each look that finds it not ready counts as a failure."""
        mill = self.world.mills[m.name]
        try:
            status = await mill.status()
        except CellctlError as e:
            self.alarms.failed(m.name, "readiness", f"not ready: {e}", alarm=False)
            return
        if status.takes_work and mill.initialized:
            awaited = self.word_awaited(m.name)
            if awaited is not None:
                # Ready, but whether its setup survived only its operator can tell.
                self.world.machines[m.name].show(f"{status.shown}; {awaited}", Condition.ALARM)
                await self.world.clock.sleep(mill.ready_wait)
                return
            self.fit[m.name] = self.ready[m.name] = True
            self.faulted.discard(m.name)
            self._overran.discard(m.name)
            self.alarms.returned(m.name, "readiness")
            if self._doubted.pop(m.name, None) is not None:
                self.alarms.log(f"{m.name}: ready again, its setup kept on the operator's word")
            elif m.setup is None:  # nothing of the cell's to keep: its operator's setup
                self.alarms.log(f"{m.name}: ready again (a part is in its vise)")
            else:
                self.alarms.log(f"{m.name}: ready again, its setup kept (a part is in its vise)")
            return
        if not mill.running:  # a block still running is no failure: it ends
            self.alarms.failed(m.name, "readiness", f"not ready: {status.shown}", alarm=False)
        elif m.name in self._overran:
            self._still_running(m.name)
        await self.world.clock.sleep(mill.ready_wait)

    async def close(self) -> None:
        """End every recovery."""
        await cancel_and_wait(self._tasks.values())

    # -- links --------------------------------------------------------------------------------

    async def reopen_closed_links(self) -> None:
        """Reopen the link of an idle machine that closed under us (a dropped connection, a
        restarted device server): its driver comes back with the host state it saved."""
        world = self.world
        robot = world.robot
        if robot is not None and robot.link.closed and not world.robot_busy():
            with contextlib.suppress(CellctlError, OSError):
                await robot.close()
            # Once: a failed step may have said so already.
            self.alarms.alarm(robot.name, "link", LINK_CLOSED)
            if self._reopen_due(robot.name):
                try:
                    world.robot = await self.links.open_robot()
                    self.alarms.log(f"{robot.name}: link reopened")
                except (CellctlError, OSError) as e:
                    self.alarms.alarm(robot.name, "link", f"cannot reopen the link: {e}")
        elif robot is not None and not robot.link.closed and self.robot_ok:
            self._reopen_at.pop(robot.name, None)  # well again: a new drop is tried at once
        for m in world.config.mills:
            if not world.mill_busy(m.name) and not await self.reopen_mill(m):
                self.fit[m.name] = False

    async def reopen_mill(self, m: MachineConfig) -> bool:
        """Reopen ``m``'s link if it closed; False if it is closed and was not reopened (it
        could not be, or its next attempt is not due yet: see module docstring)."""
        async with self._reopening.setdefault(m.name, asyncio.Lock()):
            mills = self.world.mills
            mill = mills.get(m.name)
            if mill is None or not mill.link.closed:
                if self.fit.get(m.name, False):
                    self._reopen_at.pop(m.name, None)  # well again: a new drop is tried at once
                return True
            with contextlib.suppress(CellctlError, OSError):
                await mill.close()
            if m.name not in self.faulted:  # a cut line is a fault of its own: one alarm
                self.fault(m.name, "link", LINK_CLOSED, count=False)
            if not self._reopen_due(m.name):
                return False
            try:
                mills[m.name] = await self.links.open_mill(m)
            except (CellctlError, OSError) as e:
                self.alarms.alarm(m.name, "link", f"cannot reopen the link: {e}")
                return False
            self.alarms.log(f"{m.name}: link reopened")
            return True

    def _reopen_due(self, name: str) -> bool:
        """True if an attempt to reopen ``name``'s link is due now, the next one then put
        off: the first at once, the next a poll period later, each pause twice the last up
        to :data:`REOPEN_WAIT_MAX`, until the machine is well again (a reopen that worked
        counts too: a server can take a connection and close it at once)."""
        now = self.world.clock.monotonic()
        due, wait = self._reopen_at.get(name, (now, self.world.options.poll_period))
        if now < due:
            return False
        self._reopen_at[name] = (now + wait, min(2 * wait, max(REOPEN_WAIT_MAX, wait)))
        return True

    # -- bringing machines to a known state -----------------------------------------------------

    async def prepare_robot(self, cause_of: CauseFinder | None = None) -> None:
        """Bring the robot to a known state (stopped, initialized).

        A start-up that fails is named by its cause when ``cause_of`` (the monitor's) finds
        one -- the robot's status ("servo error"), its link ("robot not answering"), the
        emergency stop -- so that the monitor's own sighting of that fault a moment later is
        the same alarm, not a second one; the robot then takes no transfer until the monitor
        finds it well (the next transfer initializes it). Only a failure nothing else
        explains is the start-up's own alarm (``initialize``), and counts as a failure.
        """
        robot = self.world.robot
        assert robot is not None
        view = self.world.machines[robot.name]
        try:
            if robot.running:
                await robot.stop()
            if not robot.ready:
                await robot.initialize()
            status = robot.host_status()
            view.show(status.text, status.condition)
            self.alarms.succeeded(robot.name)
            self.alarms.returned(robot.name, "initialize")  # a failed start-up is behind it
        except CellctlError as e:
            view.show(f"error: {e}", Condition.ALARM, LastError.of(e))
            cause = await cause_of(robot.name, e) if cause_of is not None else None
            if cause is None:
                self.alarms.failed(robot.name, "initialize", f"robot initialize failed: {e}")
                return
            self.alarms.log(f"{robot.name}: initialize failed: {e}")
            self.alarms.cause_alarm(cause)
            if cause.machine == robot.name:
                self.robot_ok = False

    async def prepare_mill(self, m: MachineConfig, *, force: bool) -> bool:
        """Initialize mill ``m`` (with its setup) unless it kept its setup; True on success.

        A failure is a fault: the mill leaves the plan, with an alarm, until a setup succeeds.
        """
        mill = self.world.mills[m.name]
        view = self.world.machines[m.name]
        believed = mill.initialized  # what the host saved: set up, as far as it knows
        try:
            # Read first: a machine power-cycled while the cell was down lost its setup,
            # whatever the host saved.
            status = await mill.status()
            if mill.running and not status.ready:
                # Left running (by a controller that was killed): no fault, but it is not
                # in the plan until recovery sees the block end.
                view.show("executing (left running)", Condition.BUSY)
                self.fit[m.name] = False
                if m.name in self._overran:
                    self._still_running(m.name)
                self._start(m.name)
                return False
            lost = believed and setup_lost(status, running=mill.running)
            if lost:
                self.alarms.log(
                    f"{m.name}: found not set up ({status.shown}): its setup was lost "
                    "(power cycled?)" + (": setting it up again" if m.setup is not None else "")
                )
            if m.setup is None and lost:
                raise SetupLost(
                    f"{m.name} lost its setup ({status.shown}) and has no setup program: "
                    "set it up at the machine"
                )
            if m.setup is not None and (force or not mill.initialized or lost):
                await mill.setup(m.setup, force=True)
                self.setup_at[m.name] = self.world.clock.monotonic()
                self.alarms.log(f"{m.name}: initialized with {m.setup.name}")
                status = await mill.status()
        except CellctlError as e:
            view.show(f"error: {e}", Condition.ALARM, LastError.of(e))
            self.fault(m.name, "initialize", f"setup failed: {e}")
            return False
        self.fit[m.name] = True
        self.faulted.discard(m.name)
        # Set up again, or returned to service by its operator: no doubt is left.
        self._doubted.pop(m.name, None)
        self._overran.discard(m.name)
        self.ready[m.name] = status.takes_work
        # Set up again: a failed setup is behind it, and a lost readiness if it takes work.
        self.alarms.returned(m.name, "initialize", *(("readiness",) if status.takes_work else ()))
        # Its operator's time for the reference zero runs from now (also after a setup sent by
        # hand while it was out of automatic service).
        self.setup_at[m.name] = self.world.clock.monotonic()
        view.show(status.shown, status.kind_condition)
        return True
