"""The mills' steps: a part machined at the mill it lies at, and the go output that starts a cycle.

A machining step journals its step, closes the mill's door and waits for the door and the vise
(``interlock_timeout``), then runs the route step's program on the mill, its progress in the
live view. Once the mill's ``run()`` was called, a failure or an emergency stop holds the part
("needs inspection"): the cell never runs a program twice on a part that may have been cut.
Only a failure the kind says positively started nothing (a
:class:`~cellctl.kinds.families.RunNotStarted` or a UsageError, with no progress but
"waiting" before it), or one before ``run()`` (the door, the vise), leaves the part where it
is, waiting. Either takes the mill out of the plan (recovery sets it up again), its alarm named by
the failure's cause; a door or vise that did not move keeps the mill from cutting until the
operator clears its alarm. A program refused before a byte went out (a UsageError: its file
changed since the cell started) is no fault of the mill's: the part waits there, held, with
an alarm saying to fix the file and release it.

The controller owns a :class:`MillSteps` and starts its :meth:`~MillSteps.machine` as a mill's
task; it needs of the controller only the world model and the alarm sink
(:mod:`cellctl.cell.ports`), and of the other parts the monitor (a failure's cause), recovery
(a faulted mill leaves the plan) and the robot's steps (the doors)::

    steps = MillSteps(
        world=c, alarms=c, monitor=c.monitor, recovery=c.recovery, robotsteps=c.robotsteps
    )
    task = asyncio.create_task(steps.machine(part_id, mill))
    mill = await open_machine(..., start_output=CallbackOutput(steps.go_pulser(m)))
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from cellctl.cell.causes import Cause, blame
from cellctl.cell.orders import ReportKind
from cellctl.cell.robotsteps import INTERLOCK_POLL_S
from cellctl.errors import CellctlError, DeviceError, UsageError
from cellctl.kinds import Condition
from cellctl.kinds.families import nothing_started
from cellctl.protocol.plc import canonical

if TYPE_CHECKING:
    from cellctl.cell.config import MachineConfig
    from cellctl.cell.monitor import Monitor
    from cellctl.cell.ports import AlarmSink, WorldModel
    from cellctl.cell.recovery import Recovery
    from cellctl.cell.robotsteps import RobotSteps
    from cellctl.kinds.families import RunProgress


class MillSteps:
    """The mills' machining steps, and their go outputs (see module docstring)."""

    def __init__(
        self,
        world: WorldModel,
        alarms: AlarmSink,
        monitor: Monitor,
        recovery: Recovery,
        robotsteps: RobotSteps,
    ) -> None:
        self.world = world
        self.alarms = alarms
        self.monitor = monitor
        self.recovery = recovery
        self.robotsteps = robotsteps

    def go_coil(self, m: MachineConfig) -> str:
        """The PLC coil that starts mill ``m``'s cycle (its ``go_output``, else ``go_N``)."""
        return canonical(m.go_output or f"go_{self.world.mill_index(m.name)}")

    def go_pulser(self, m: MachineConfig) -> Callable[[], Any]:
        """What mill ``m``'s driver calls to start a cycle: a 50 ms pulse of its go coil."""
        coil = self.go_coil(m)

        async def pulse() -> None:
            plc = self.world.plc
            assert plc is not None
            await plc.pulse(coil, 0.05)

        return pulse

    async def machine(self, part_id: str, mill_name: str) -> None:
        """Machine part ``part_id`` at mill ``mill_name``, where it lies: its route's next step
        (see module docstring). Started by dispatch as the mill's task."""
        mill = self.world.mills[mill_name]
        view = self.world.machines[mill_name]
        part = self.world.journal.get_part(part_id)
        route = self.world.config.parts[part.part_type].route
        route_step = route[part.route_index]
        step = self.world.journal.begin_step(part.id, "machine", mill_name, route_step.name)
        self.world.mailbox.post_report(
            ReportKind.STEP_STARTED,
            f"{mill_name} {route_step.name} {part.id}",
            order_id=part.order_id,
            part_id=part.id,
        )
        view.step = f"{route_step.name} ({part.id})"
        view.show("machining", Condition.BUSY)
        started = self.world.clock.monotonic()
        since = self.world.clock.now()
        index = self.world.mill_index(mill_name)
        plc = self.world.plc
        assert plc is not None
        cutting = False  # run() was called: the part may be cut (unless the kind says not)
        phases: set[str] = set()  # the progress phases run() reported
        try:
            with blame("plc", "PLC"):
                # Close the door (a transfer cut short by a restart may have left it open).
                await self.robotsteps.doors([mill_name], False)
                await self.robotsteps.door_closed(mill_name)
                # The vise was commanded by the robot's program (when, the host cannot
                # know): read at the poll's rate, mostly closed already.
                await plc.wait_for(
                    f"clamp_closed_{index}",
                    True,
                    timeout=self.world.options.interlock_timeout,
                    poll=INTERLOCK_POLL_S,
                )

            def progress(p: RunProgress) -> None:
                phases.add(p.phase)
                if view.report_run(p, route_step.name, since):
                    self.alarms.touch()

            cutting = True
            await mill.run(route_step.program, progress=progress)
        except (CellctlError, OSError, asyncio.CancelledError) as e:
            cutting = cutting and not nothing_started(e, phases)
            # A failed step's time was the machine's too (the shift report's counts it): the
            # live figure does not drop as the step ends.
            view.busy_s += self.world.clock.monotonic() - started
            view.step = ""
            view.progress = None
            stopped = isinstance(e, asyncio.CancelledError)
            what = f"cut short by {self.world.cancel_reason}" if stopped else f"failed: {e}"
            if cutting:
                reason = f"needs inspection: machining {route_step.name} on {mill_name} {what}"
                self.world.journal.end_step(step.id, "failed", str(e) or what, hold=reason)
                self.world.mailbox.post_report(
                    ReportKind.PART_HELD, reason, order_id=part.order_id, part_id=part.id
                )
            elif stopped:
                # A stop holds every part in flight for the operator; this one was not cut
                # (nothing of the program went out).
                reason = (
                    f"{self.world.cancel_reason} before machining {route_step.name} on {mill_name}"
                )
                self.world.journal.end_step(step.id, "failed", what, hold=reason)
                self.world.mailbox.post_report(
                    ReportKind.PART_HELD, reason, order_id=part.order_id, part_id=part.id
                )
            elif isinstance(e, UsageError):
                # The program itself was refused before a byte went out (a file changed
                # since the cell started): no fault of the mill's, and trying again would
                # refuse it again. The part waits, held, for the file to be put right.
                reason = (
                    f"program {route_step.program.name} refused for {route_step.name} on "
                    f"{mill_name}: {e}: fix the file, then `cellctl part release {part.id} "
                    "--redo`"
                )
                self.world.journal.end_step(step.id, "failed", str(e), hold=reason)
                self.world.mailbox.post_report(
                    ReportKind.PART_HELD, reason, order_id=part.order_id, part_id=part.id
                )
            else:
                # Nothing of the program went out: the part is as it was, and waits there.
                reason = f"machining {route_step.name} on {mill_name} not started: {what}"
                self.world.journal.end_step(step.id, "failed", str(e) or what)
            self.world.mailbox.post_report(
                ReportKind.STEP_FAILED, reason, order_id=part.order_id, part_id=part.id
            )
            if stopped:
                self.alarms.wake()
                raise
            if isinstance(e, UsageError) and not cutting:
                self.alarms.cause_alarm(Cause(mill_name, "program", reason))
                view.show(mill.state_text, Condition.IDLE)
                self.alarms.wake()
                return
            # Out of the plan at once; recovery sets it up again (reopening its link). The
            # alarm names the cause: the PLC, the mill's link, or the step itself.
            cause = await self.monitor.cause_of(mill_name, e)
            if isinstance(e, DeviceError) and mill.running:
                # The machine failed the step while its block runs on (past its deadline):
                # one still running later is the fault, not a block that ends by itself.
                self.recovery.overran(mill_name)
            if cause is not None and cause.code == "interlock":
                # A door or vise that did not move: this mill cuts nothing until the operator
                # clears the alarm (each try would close the door and wait out its deadline
                # again, for ever), as transfers wait for it.
                self.recovery.interlocked(mill_name)
            self.recovery.fault(mill_name, "machining", reason, cause=cause)
            self.alarms.wake()
            return
        view.progress = None
        view.busy_s += self.world.clock.monotonic() - started
        view.step = ""
        view.show(mill.state_text, Condition.IDLE)
        self.recovery.ready[mill_name] = True  # the last block ended with CTS high
        self.alarms.succeeded(mill_name)
        self.world.journal.end_step(step.id, "finished", route_index=part.route_index + 1)
        self.world.mailbox.post_report(
            ReportKind.STEP_FINISHED,
            f"{mill_name} {route_step.name} {part.id}",
            order_id=part.order_id,
            part_id=part.id,
        )
        self.alarms.wake()
