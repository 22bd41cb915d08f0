"""The cell controller: orders in, robot and mill tasks out, every machine watched.

::

    controller = CellController(load_cell("cell"), open_journal("cell"), open_mailbox("cell"))
    await controller.connect()
    await controller.run(stop_event)          # until stop_event is set: then finishes steps

Parts of the reference model (spec ``cell.md``):

- **M, the world model**: :attr:`CellController.machines` (each machine's state, its current
  step, whether it is in service), the journal's parts (where each part is, how far along its
  route), the robot's partitions (which program where, kept by its kind), the PLC's inputs.
- **H, task decomposition and scheduling**: an accepted order becomes parts in the journal;
  :mod:`cellctl.cell.scheduler` picks the robot's next transfer, and a part that reaches a mill
  is machined there at once (:mod:`cellctl.cell.millsteps`). Robot programs stay in the 5
  partitions and are downloaded again only when evicted (least recently used first).
- **G, monitoring** (:mod:`cellctl.cell.monitor`): four times a ``poll_period`` the PLC
  inputs, the idle robot's status and each idle mill's readiness are read; a fault becomes an
  alarm (journal + report) within one poll period, named by its cause whoever sees it first
  (:mod:`cellctl.cell.causes`). A busy machine is watched by its own step.
- **Recovery** (:mod:`cellctl.cell.recovery`): work goes only to a mill whose setup succeeded
  since its last initialization or fault and whose last poll said ready; a failed setup, a lost
  readiness or a stall takes it out of the plan at once, and it is initialized again with force
  until it can take work. A robot reject is read (the driver does), reset and retried
  ``retries`` times. A machine that keeps failing (``fail_limit`` in a row) is taken out of
  service; clearing its alarm (``cellctl alarm clear ID``) returns it to service. A part a
  mill never started cutting stays where it is, waiting, never held as "needs inspection".
- **Journal**: every step is written before it starts and after it ends. At start
  :meth:`Journal.recover` holds every part whose step was in flight: a machining step is
  never restarted automatically ("needs inspection"), and neither is a transfer.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable

from cellctl.cell.causes import Cause, link_cause
from cellctl.cell.commands import OperatorCommands
from cellctl.cell.config import CONVEYOR, CellConfig, MachineConfig
from cellctl.cell.journal import Journal
from cellctl.cell.machines import open_machine
from cellctl.cell.millsteps import MillSteps
from cellctl.cell.model import (
    DEFAULT_DONE_OUTPUT,
    TRAFFIC_KEPT,
    ControllerOptions,
    Event,
    MachineView,
    NotifyingMailbox,
)
from cellctl.cell.monitor import Monitor
from cellctl.cell.orderflow import OUT, OrderFlow
from cellctl.cell.orders import OrderBox, ReportKind
from cellctl.cell.physics import physical_durations
from cellctl.cell.recovery import Recovery
from cellctl.cell.robotsteps import RobotSteps
from cellctl.cell.scheduler import SHORTEST_FIRST
from cellctl.cell.vises import EmptiedVises
from cellctl.cell.workview import WorkView
from cellctl.clock import Clock, current_clock
from cellctl.drivers.plc import ModbusPlc
from cellctl.drivers.state import StateStore
from cellctl.errors import CellctlError
from cellctl.kinds.families import CallbackOutput, Mill, Robot
from cellctl.link import TrafficLog
from cellctl.protocol.plc import PlcMap
from cellctl.tasks import cancel_and_wait

#: Why the steps in flight were cancelled when nothing said otherwise: the controller itself
#: was ended (a second Ctrl-C, the service stopped hard), not an emergency stop.
ABORTED = "the controller's abort"


class CellController(OperatorCommands):
    """Runs a cell from its ``cell.toml``, journal and mailbox (see module docstring).

    The operator's commands (pause, service, manual use, emergency stop) are in
    :class:`~cellctl.cell.commands.OperatorCommands`; the robot's transfers in
    :class:`~cellctl.cell.robotsteps.RobotSteps`; the mills' machining in
    :class:`~cellctl.cell.millsteps.MillSteps`.
    """

    def __init__(
        self,
        config: CellConfig,
        journal: Journal,
        mailbox: OrderBox,
        *,
        options: ControllerOptions | None = None,
        on_event: Callable[[Event], None] | None = None,
        clock: Clock | None = None,
    ) -> None:
        self._clock = clock
        self._init_commands()
        self.config = config
        self.journal = journal
        self.mailbox: OrderBox = NotifyingMailbox(mailbox, self.touch)
        self.traffic = TrafficLog(None, keep=TRAFFIC_KEPT)
        self.options = options or ControllerOptions.from_config(config)
        #: The machines' state files (partitions, a mill's setup, coils left high).
        self.store = StateStore(config.directory, durable=self.options.durable)
        self.on_event = on_event
        self.robot: Robot | None = None
        self.mills: dict[str, Mill] = {}
        self.plc: ModbusPlc | None = None
        self.plc_map = PlcMap.from_toml(config.plc)
        self.machines: dict[str, MachineView] = {
            m.name: MachineView(m.name, m.kind) for m in [config.robot, *config.mills]
        }
        self.events: list[Event] = []
        self.inputs: dict[str, bool] = {}
        self._wake = asyncio.Event()
        # The parts see the controller through the narrow interfaces of cell.ports only.
        self.recovery = Recovery(world=self, alarms=self, links=self)
        self.monitor = Monitor(world=self, alarms=self, plc=self, recovery=self.recovery)
        self.orderflow = OrderFlow(world=self, alarms=self)
        self.workview = WorkView(world=self, alarms=self, orderflow=self.orderflow)
        self.vises = EmptiedVises(world=self, alarms=self)
        self.robotsteps = RobotSteps(
            world=self, alarms=self, plc=self, monitor=self.monitor, recovery=self.recovery
        )
        self.millsteps = MillSteps(
            world=self,
            alarms=self,
            monitor=self.monitor,
            recovery=self.recovery,
            robotsteps=self.robotsteps,
        )
        self._robot_task: asyncio.Task[None] | None = None
        self._mill_tasks: dict[str, asyncio.Task[None]] = {}
        self._pallet_requested = False
        self._pallet_requested_at = 0.0  # monotonic, for the deadline
        self._pallet_asked_wall = 0.0  # wall time, to compare with an alarm's clearing
        # (machine, code) of open alarms not yet returned to normal, so that the monitor's
        # every look costs no journal read (None: not read from the journal yet).
        self._unreturned: set[tuple[str, str]] | None = None
        self._pallet_pulse: asyncio.Task[None] | None = None
        self._stopping = False
        self.cancel_reason = ABORTED
        self._work: dict[str, float] | None = None
        self.started_at = self.clock.now()
        self._noted_start = False  # "started" journaled: close() journals "stopped"

    # -- plumbing ---------------------------------------------------------------------------------

    @property
    def clock(self) -> Clock:
        """What the cell reads the time from and waits on: the clock given, else the running
        loop's (a controller may be made before its loop runs); its drivers get the same."""
        return self._clock or current_clock()

    def log(self, text: str) -> None:
        """Note an event (kept for the live view, passed to ``on_event``)."""
        event = Event(self.clock.now(), text)
        self.events.append(event)
        del self.events[:-200]
        if self.on_event is not None:
            self.on_event(event)
        self.touch()

    def wake(self) -> None:
        """Let the dispatch loop look again now (a step ended, a fault changed the plan)."""
        self._wake.set()

    @property
    def stopping(self) -> bool:
        """True once the cell was told to stop: steps in flight finish, none starts."""
        return self._stopping

    def mill_index(self, name: str) -> int:
        """Mill ``name``'s number (1, 2, ...) in the PLC's wiring."""
        return [m.name for m in self.config.mills].index(name) + 1

    def alarm(self, machine: str, code: str, text: str) -> None:
        """Raise an alarm, unless ``machine`` has an active one with this ``code``: a fault
        seen again, or seen through its effects, adds nothing (see :mod:`cellctl.cell.causes`);
        once the operator clears it, a fault still there is raised again."""
        a = self.journal.open_alarm(machine, code)
        if a is not None:
            if a.returned is not None:  # its condition is back: unacknowledged again
                self.journal.reactivate(a.id)
                self._watch(machine, code)
                self.log(f"ALARM {a.id} {machine}: active again: {text}")
            return
        alarm, new = self.journal.raise_alarm(machine, code, text)
        self._watch(machine, code)
        if new:
            self.mailbox.post_report(
                ReportKind.ALARM_RAISED, f"{machine}: {text}", data={"alarm": alarm.id}
            )
            self.log(f"ALARM {alarm.id} {machine}: {text}")

    def returned(self, machine: str, *codes: str) -> None:
        """The condition behind ``machine``'s open alarms with ``codes`` is gone (a look
        found it well): they are returned to normal, and stay open until cleared."""
        if self._unreturned is None:
            self._unreturned = {
                (a.machine, a.code) for a in self.journal.active_alarms() if a.returned is None
            }
        if not self._unreturned:
            return  # nothing open to return: the monitor's usual look costs nothing
        watched = [code for code in codes if (machine, code) in self._unreturned]
        if not watched:
            return
        for a in self.journal.return_to_normal(machine, watched):
            self.log(f"alarm {a.id} {machine}: returned to normal ({a.text})")
        self._unreturned -= {(machine, code) for code in watched}

    def _watch(self, machine: str, code: str) -> None:
        if self._unreturned is not None:
            self._unreturned.add((machine, code))

    def cause_alarm(self, cause: Cause) -> None:
        """The alarm of ``cause`` (only logged if its alarm was cleared while it was out)."""
        if cause.told:  # a step under way when the operator cleared this fault's alarm
            self.log(f"{cause.machine}: {cause.text} (its alarm already cleared)")
            return
        self.alarm(cause.machine, cause.code, cause.text)

    def failed(self, machine: str, code: str, text: str, *, alarm: bool = True) -> None:
        """A machine failed a step: alarm, and out of service after ``fail_limit`` in a row."""
        view = self.machines[machine]
        view.failures += 1
        if alarm:
            self.alarm(machine, code, text)
        if view.failures >= self.options.fail_limit and view.in_service:
            view.in_service = False
            reason = f"failed {view.failures} times in a row: {text}"
            self.journal.set_machine_service(machine, False, reason)
            self.alarm(machine, "out-of-service", f"taken out of service: {reason}")

    def succeeded(self, machine: str) -> None:
        """A machine did its step: its failures in a row start again from 0."""
        self.machines[machine].failures = 0

    def step_task(self, name: str) -> asyncio.Task[None] | None:
        """The step running on machine ``name``, if any."""
        task = self._robot_task if name == self.config.robot.name else self._mill_tasks.get(name)
        return task if task is not None and not task.done() else None

    def steps_in_flight(self) -> list[asyncio.Task[None]]:
        """The steps running now (the robot's transfer, each mill's machining)."""
        tasks = [self._robot_task, *self._mill_tasks.values()]
        return [t for t in tasks if t is not None and not t.done()]

    def plc_view(self) -> MachineView:
        """The PLC's line in the live view (added on the first poll)."""
        view = self.machines.get("plc")
        if view is None:
            view = self.machines["plc"] = MachineView("plc", "plc")
        return view

    # -- connecting -------------------------------------------------------------------------------

    async def connect(self) -> None:
        """Open every machine's link and bring each to a known state; recover the journal."""
        recovery = self.journal.recover()
        # The controller's life, for the shift report's running, paused and stopped time.
        self.journal.note_controller("started")
        self._noted_start = True
        for step in recovery.interrupted:
            self.log(f"restart: {step.kind} {step.program} of part {step.part_id} was in flight")
        for part in recovery.held:
            self.mailbox.post_report(
                ReportKind.PART_HELD, part.note, order_id=part.order_id, part_id=part.id
            )
            self.log(f"part {part.id} held: {part.note}")
        for name in self.journal.machines_out_of_service():
            if name in self.machines:
                self.machines[name].in_service = False
        self.plc = await ModbusPlc.connect(
            self.plc_map.url,
            self.plc_map,
            clock=self._clock,
            store=self.store,
        )
        # A controller killed mid-pulse leaves that coil high: this one's first pulse would
        # make no rising edge, and the conveyor or the mill would never hear it.
        for coil in ["pallet_request", *(self.millsteps.go_coil(m) for m in self.config.mills)]:
            await self.plc.write(coil, False)
        self.robot = await self.open_robot()
        for m in self.config.mills:
            self.mills[m.name] = await self.open_mill(m)
        await self.prepare_robot()
        for m in self.config.mills:
            await self.prepare_mill(m, force=False)
        self.log(f"connected to {', '.join(self.machines)} and the PLC: running")

    async def open_robot(self) -> Robot:
        """The robot's driver, built from its config, its link open."""
        r = self.config.robot
        robot: Robot = await open_machine(
            r.kind,
            r.name,
            r.link,
            r.line,
            r.options,
            store=self.store,
            trace=self.traffic,
            clock=self._clock,
        )
        return robot

    async def open_mill(self, m: MachineConfig) -> Mill:
        """Mill ``m``'s driver, built from its config, its link open."""
        mill: Mill = await open_machine(
            m.kind,
            m.name,
            m.link,
            m.line,
            m.options,
            store=self.store,
            trace=self.traffic,
            start_output=CallbackOutput(self.millsteps.go_pulser(m)),
            clock=self._clock,
        )
        return mill

    def robot_busy(self) -> bool:
        """True while a transfer runs."""
        return self._robot_task is not None and not self._robot_task.done()

    def mill_busy(self, name: str) -> bool:
        """True while mill ``name`` machines a part."""
        task = self._mill_tasks.get(name)
        return task is not None and not task.done()

    async def prepare_robot(self) -> None:
        """Bring the robot to a known state (stopped, initialized), as on connecting; a
        failure is alarmed by its cause (the monitor's), whoever sees it next."""
        await self.recovery.prepare_robot(self.monitor.cause_of)

    async def prepare_mill(self, m: MachineConfig, *, force: bool) -> bool:
        """Bring mill ``m`` to a known state (its setup); True if it may take work."""
        return await self.recovery.prepare_mill(m, force=force)

    def halted(self, name: str) -> None:
        """Mill ``name`` was sent END by an emergency stop: initialized again on resume."""
        self.recovery.halted(name)

    def resume_halted(self) -> None:
        """Initialize again the mills an emergency stop halted (the cell resumes)."""
        self.recovery.resume_halted()

    async def close(self) -> None:
        """Close every link. Steps still in flight (a run cancelled, not stopped) end first,
        cut short as a crash would leave them: their parts are held at the next start."""
        if self._noted_start:  # once, however often it is closed
            self._noted_start = False
            self.journal.note_controller("stopped")
        await cancel_and_wait(self.steps_in_flight())
        if self._pallet_pulse is not None:
            with contextlib.suppress(Exception):
                await self._pallet_pulse  # 50 ms at most: the coil goes low before the link
        await self.recovery.close()
        for mill in self.mills.values():
            await mill.close()
        if self.robot is not None:
            await self.robot.close()
        if self.plc is not None:
            await self.plc.close()

    # -- the loop ---------------------------------------------------------------------------------

    async def run(self, stop: asyncio.Event, *, until_idle: bool = False) -> None:
        """Run until ``stop`` is set (or, with ``until_idle``, until no order is open).

        On stop no new step starts; steps in flight finish, then it returns.
        """
        monitor = asyncio.create_task(self.monitor.run())
        try:
            while True:
                # Cleared before the round, not after: a step that ends while dispatch awaits
                # the PLC must wake the next round, not wait out a poll period.
                self._wake.clear()
                self._stopping = stop.is_set()
                self.orderflow.intake()
                self.orderflow.sync_operator()
                if not self._stopping and not self.paused:
                    await self.recovery.reopen_closed_links()
                    await self._dispatch()
                busy = self._busy()
                if self._stopping and not busy:
                    break
                if until_idle and not busy and self.orderflow.all_orders_closed():
                    break
                with contextlib.suppress(TimeoutError):
                    async with self.clock.timeout(self.options.poll_period):
                        await self._wake.wait()
        finally:
            # Let the monitor finish its round: cancelling it mid-request would strand a
            # Modbus or serial transaction.
            self.monitor.done.set()
            try:
                async with self.clock.timeout(10):
                    await monitor
            except TimeoutError:
                monitor.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await monitor

    def _busy(self) -> bool:
        return bool(self.steps_in_flight())

    # -- dispatch ---------------------------------------------------------------------------------

    def _estop_pressed(self) -> None:
        """The PLC's emergency stop is pressed: the cell pauses, as for ``cellctl estop``.
        Releasing the button restarts nothing (a reset must never start a machine): the
        operator clears its alarm, then resumes."""
        if not self.paused:
            self.paused = True
            self.journal.note_controller("paused", why="emergency stop pressed")
            self.log(
                "emergency stop pressed: cell paused; once it is released, clear its alarm, "
                "then resume"
            )

    async def _dispatch(self) -> None:
        if not self.inputs.get("estop_ok", True):
            self._estop_pressed()
            return
        work = self.workview.current()
        in_service = {n for n, v in self.machines.items() if v.in_service}
        # Mills: a part at a mill not yet machined there is cut now.
        for part_id, mill in work.to_machine:
            task = self._mill_tasks.get(mill)
            if mill in in_service and (task is None or task.done()) and self.recovery.usable(mill):
                self._mill_tasks[mill] = asyncio.create_task(self.millsteps.machine(part_id, mill))
        robot_name = self.config.robot.name
        if robot_name not in in_service:
            return
        if self._robot_task is not None and not self._robot_task.done():
            return
        if not self.recovery.robot_may_move():
            return  # a robot fault, a stuck door: no transfer until found well or cleared
        try:
            await self.read_inputs()
        except CellctlError:
            return
        if not self.inputs.get("estop_ok", True):
            self._estop_pressed()
            return
        pallet = self.inputs.get("pallet_present", False)
        if pallet:
            # The request was served, whether the pallet is taken now or waits: a transfer
            # that lifts it away must not leave the request standing, overdue.
            self._pallet_requested = False
        outfeed = self.inputs.get("outfeed_clear", True)
        # A place a held part may occupy takes no part: it counts as out of service here; so
        # does a mill whose setup failed or whose last poll did not say ready.
        usable_mills = (in_service - work.blocked - self.recovery.unusable()) | {CONVEYOR}
        # A mill emptied by hand takes no part until its vise is open: the robot opens it
        # first (cellctl.cell.vises).
        vises = self.vises.look(work, self.inputs)
        if vises.to_open is not None:
            self._robot_task = asyncio.create_task(self.robotsteps.open_vise(vises.to_open))
            return
        transfer = self.workview.next_transfer(
            work,
            mills_in_service=usable_mills - vises.waiting,
            pallet_present=pallet,
            outfeed_clear=outfeed,
            policy=self.options.policy,
            work_s=self._work_s(),
        )
        if transfer is None:
            await self._request_pallet(work.waiting_on_conveyor, pallet)
            return
        self._robot_task = asyncio.create_task(self.robotsteps.transfer(transfer))

    def _work_s(self) -> dict[str, float] | None:
        """Seconds of machining per part type, for the shortest-first policy (from the
        machines' models, worked out once)."""
        if self.options.policy != SHORTEST_FIRST:
            return None
        if self._work is None:
            phys = physical_durations(self.config)
            self._work = {
                name: sum(phys.machining_s[(s.mill, s.name)] for s in part.route)
                for name, part in self.config.parts.items()
            }
        return self._work

    async def read_inputs(self) -> dict[str, bool]:
        """Read the PLC's inputs now (kept in :attr:`inputs`)."""
        assert self.plc is not None
        self.inputs = await self.plc.read_inputs()
        return self.inputs

    async def _request_pallet(self, waiting: bool, present: bool) -> None:
        """Ask the conveyor for a pallet when a part waits to start and none is there."""
        if present:
            return
        if not waiting or self.plc is None:
            return
        if not self._pallet_requested and (self._pallet_pulse is None or self._pallet_pulse.done()):
            # The conveyor answers the rising edge; the pulse's 50 ms go on in the background,
            # so a mill that finishes meanwhile is served at once.
            self._pallet_requested = True
            # The edge is at the pulse's start.
            self._pallet_requested_at = self.clock.monotonic()
            self._pallet_asked_wall = self.clock.now()
            self._pallet_pulse = asyncio.create_task(self._pulse_pallet())

    async def _pulse_pallet(self) -> None:
        assert self.plc is not None
        try:
            await self.plc.pulse("pallet_request", 0.05)
        except CellctlError as e:
            self._pallet_requested = False
            # A PLC that does not answer is that fault's one alarm, not a conveyor's.
            cause = link_cause("plc", "PLC", e)
            if cause is not None:
                self.cause_alarm(cause)
            else:
                self.alarm("plc", "conveyor", f"cannot request a pallet: {e}")
            self.wake()

    def pallet_taken(self) -> None:
        """The robot lifted a pallet off the conveyor: a request standing is served."""
        self._pallet_requested = False

    def pallet_overdue(self) -> None:
        """The monitor's look at a requested pallet: none there ``pallet_timeout`` after the
        request means the conveyor lost it or is stuck: say so, and let dispatch ask again.

        A request is over, and dispatch asks again if it still needs one, once a pallet is
        seen (the robot may lift it before dispatch looks), once an emergency stop halted
        the conveyor (asked again after the release), and once the operator cleared the
        conveyor's alarm after the request went out: that request was made of the conveyor
        before it was fixed, and is asked again now rather than alarmed a second time.
        """
        if not self._pallet_requested:
            return
        if self.inputs.get("pallet_present", False) or not self.inputs.get("estop_ok", True):
            self._pallet_requested = False
            if self.inputs.get("pallet_present", False):
                self.returned("plc", "conveyor")
            return
        if any(
            a.machine == "plc"
            and a.code == "conveyor"
            and a.cleared is not None
            and a.cleared >= self._pallet_asked_wall
            for a in self.journal.alarms()
        ):
            self._pallet_requested = False
            self.log("conveyor: its alarm cleared: the pallet is asked for again")
            self._wake.set()
            return
        if self.clock.monotonic() - self._pallet_requested_at > self.options.pallet_timeout:
            self.alarm(
                "plc",
                "conveyor",
                f"no pallet within {self.options.pallet_timeout:g} s of the request",
            )
            self._pallet_requested = False
            self.wake()


__all__ = [
    "DEFAULT_DONE_OUTPUT",
    "OUT",
    "CellController",
    "ControllerOptions",
    "Event",
    "MachineView",
]
