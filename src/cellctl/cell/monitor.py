"""G, monitoring: every poll period, read what is idle and turn what matters into alarms.

One round reads the PLC's inputs (emergency stop, a PLC that stopped answering), the idle
robot's machine status (servo error, power failure, a silent or closed line) and each idle
mill's readiness (CTS): the last poll of a mill is what the scheduler trusts (see
:class:`~cellctl.cell.recovery.Recovery`). A mill that lost readiness while idle, or that was
not ready ``setup_timeout`` after its setup, or whose line fails, is a fault: out of the plan
at once, one alarm. A busy machine is watched by its own step's deadlines; a machine in the
operator's manual use is left alone. Every round ends with the controller's ``_touch()``.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import TYPE_CHECKING

from cellctl.drivers.robot import ROBOT_STATES
from cellctl.errors import CellctlError, UsageError

if TYPE_CHECKING:
    from cellctl.cell.config import MachineConfig
    from cellctl.cell.controller import CellController


class Monitor:
    """The controller's monitoring rounds (see module docstring)."""

    def __init__(self, controller: CellController) -> None:
        self.ctl = controller
        self.done = asyncio.Event()

    async def run(self) -> None:
        """Rounds until :attr:`done` is set (a round in progress finishes first)."""
        while not self.done.is_set():
            await self.round()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.ctl.options.poll_period):
                    await self.done.wait()

    async def round(self) -> None:
        ctl = self.ctl
        await self._plc()
        await self._robot()
        for m in ctl.config.mills:
            task = ctl._mill_tasks.get(m.name)
            if (task is not None and not task.done()) or m.name in ctl.manual_use:
                continue
            await self._mill(m)
        ctl._wake.set()
        ctl._touch()

    async def _plc(self) -> None:
        ctl = self.ctl
        view = ctl.plc_view()
        try:
            inputs = await ctl._read_inputs()
        except CellctlError as e:
            view.state = f"error: {e}"
            ctl._alarm("plc", "link", "PLC not answering")
            return
        view.state = "ok"
        if not inputs.get("estop_ok", True):
            ctl._alarm("plc", "estop", "emergency stop: the cell is stopped")
            view.state = "emergency stop"

    async def _robot(self) -> None:
        ctl = self.ctl
        robot = ctl.robot
        if robot is None or ctl._robot_busy() or robot.name in ctl.manual_use:
            return
        view = ctl.machines[robot.name]
        period = ctl.options.poll_period
        try:
            # A status read takes a few tens of ms: one that outlasts a poll period is a
            # silent controller, told now rather than at the driver's own deadline.
            async with asyncio.timeout(period):
                status = await robot.machine_status()
        except TimeoutError:
            view.state = "not answering"
            ctl._alarm(robot.name, "link", f"robot not answering within {period:g} s")
            return
        except CellctlError as e:
            view.state = f"error: {e}"
            ctl._alarm(robot.name, "link", f"robot not answering: {e}")
            return
        if not status.ok:
            ctl._alarm(robot.name, "status", str(status))
            view.state = str(status)
        else:
            view.state = ROBOT_STATES.get(robot.state, str(robot.state))

    async def _mill(self, m: MachineConfig) -> None:
        ctl = self.ctl
        recovery = ctl.recovery
        view = ctl.machines[m.name]
        mill = ctl.mills.get(m.name)
        if mill is None:
            return
        try:
            status = await mill.status()
        except (CellctlError, UsageError) as e:
            view.state = f"error: {e}"
            if view.in_service:
                recovery.fault(m.name, "link", f"mill not answering: {e}", count=False)
            return
        view.state = status.state_text + (f", {status.condition}" if status.condition else "")
        was_ready = recovery.ready.get(m.name, False)
        ready = status.ready and status.state == 2
        recovery.ready[m.name] = ready and recovery.fit.get(m.name, False)
        if not view.in_service or not recovery.fit.get(m.name, False):
            return
        if was_ready and not ready and status.state == 2:
            # CTS low on an idle, set-up mill that is not waiting for its operator.
            recovery.fault(m.name, "readiness", "lost readiness (CTS low while idle)", count=False)
        elif status.state == 1 and not status.ready and mill.initialized:
            since = recovery.setup_at.get(m.name, time.monotonic())
            if time.monotonic() - since > mill.config.setup_timeout:
                recovery.fault(
                    m.name,
                    "readiness",
                    f"not ready: {status.condition or 'CTS low'} "
                    f"{mill.config.setup_timeout:g} s after its setup",
                    count=False,
                )
