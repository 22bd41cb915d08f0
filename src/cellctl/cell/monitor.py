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
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any, TypeVar

from cellctl.drivers.robot import ROBOT_STATES
from cellctl.errors import CellctlError, UsageError

if TYPE_CHECKING:
    from cellctl.cell.config import MachineConfig
    from cellctl.cell.controller import CellController


T = TypeVar("T")


class _StillOut(Exception):
    """The machine's last read has not ended yet: this round does not ask again."""


def _consume(task: asyncio.Future[Any]) -> None:
    """Retrieve a late read's outcome (its failure was told as an alarm already)."""
    if not task.cancelled():
        task.exception()


class Monitor:
    """The controller's monitoring rounds (see module docstring)."""

    def __init__(self, controller: CellController) -> None:
        self.ctl = controller
        self.done = asyncio.Event()
        self._reads: dict[str, asyncio.Future[Any]] = {}

    async def _bounded(self, key: str, read: Callable[[], Awaitable[T]]) -> T:
        """``read()`` of an idle machine, awaited at most ``read_limit`` (TimeoutError after).

        A status exchange takes tens of milliseconds: one that outlasts the limit is a silent
        machine, told now rather than at the driver's own deadline. The read is not cancelled
        (cut mid-exchange it would leave the line out of step): it ends by itself, and until
        it has, the next rounds raise :class:`_StillOut` instead of asking again.
        """
        pending = self._reads.get(key)
        if pending is not None and not pending.done():
            raise _StillOut
        future = asyncio.ensure_future(read())
        self._reads[key] = future
        try:
            return await asyncio.wait_for(asyncio.shield(future), self.ctl.options.read_limit)
        except TimeoutError:
            future.add_done_callback(_consume)
            raise

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
            inputs = await self._bounded("plc", ctl._read_inputs)
        except _StillOut:
            return
        except TimeoutError:
            view.state = "not answering"
            ctl._alarm("plc", "link", f"PLC not answering within {ctl.options.read_limit:g} s")
            return
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
        try:
            status = await self._bounded(robot.name, robot.machine_status)
        except _StillOut:
            return  # the last read is still out (and already told as not answering)
        except TimeoutError:
            view.state = "not answering"
            limit = ctl.options.read_limit
            ctl._alarm(robot.name, "link", f"robot not answering within {limit:g} s")
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
