"""The plan's operator: what the people at the cell do during a plan's fault windows.

:func:`cellctl.plan.engine.simulate` makes one per play and runs :meth:`PlanOperator.window`
for each window::

    operator = PlanOperator(controller, cell, journal, kept_out=inputs.out_of_service)
    await operator.window(FaultWindow("cnc2", "down", start, end), until)

A "down" window takes the machine out of service and back; any other switches the emulator's
fault on and off, and afterwards the operator resolves what the cell holds.
"""

from __future__ import annotations

import contextlib
from collections import Counter
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from cellctl.clock import current_clock
from cellctl.errors import UsageError

if TYPE_CHECKING:
    from cellctl.cell.controller import CellController
    from cellctl.cell.journal import Journal
    from cellctl.emulators.cell import EmulatedCell
    from cellctl.plan.engine import FaultWindow

__all__ = ["RESOLVE_LOOKS", "RESOLVE_ROUNDS", "PlanOperator"]

#: The plan's operator, after a fault: looks (poll periods) of rest before acting, and how
#: many times at most the rest of the cell is looked over and resolved again.
RESOLVE_LOOKS = 4
RESOLVE_ROUNDS = 5


class PlanOperator:
    """The plan's operator: takes a machine out and back for "down", switches an emulator's
    fault on and off, and afterwards resolves what the cell holds (as an operator does: the
    alarms cleared, each held part released where it physically is)."""

    def __init__(
        self,
        controller: CellController,
        cell: EmulatedCell,
        journal: Journal,
        kept_out: Iterable[str] = (),
    ) -> None:
        self.controller = controller
        self.cell = cell
        self.journal = journal
        # Out of service when the plan began: they stay out, whatever window closes.
        self.kept_out = frozenset(kept_out)
        # Windows open now per (machine, fault): overlapping ones act as their union.
        self._open: Counter[tuple[str, str]] = Counter()

    async def window(self, fault: FaultWindow, until: float) -> None:
        clock = current_clock()
        key = (fault.machine, fault.fault)
        await clock.sleep(max(0.0, fault.start - clock.now()))
        self._open[key] += 1
        if self._open[key] == 1:
            await self._switch_on(fault)
        if fault.end is None or fault.end >= until:
            return
        await clock.sleep(max(0.0, fault.end - clock.now()))
        self._open[key] -= 1
        if self._open[key] > 0:
            return  # another window of the same fault is still open
        if fault.fault == "down":
            if fault.machine not in self.kept_out:
                await self.controller.set_service(fault.machine, True)
            return
        await self._switch_off(fault.machine, fault.fault)
        await self.resolve(until, fault.end)

    async def _switch_on(self, fault: FaultWindow) -> None:
        if fault.fault != "down":
            # A line noise with no SEED of its own draws from the plan's seed.
            self.cell.set_fault(fault.machine, fault.fault, fault.arg)
        elif fault.machine not in self.kept_out:
            await self.controller.set_service(fault.machine, False, "down (plan)")

    def _target(self, machine: str) -> Any:
        return self.cell.machine(machine)

    async def _switch_off(self, machine: str, name: str) -> None:
        """The fault off, and what the panel needs after it (as ``CellRig.switch_off``)."""
        target = self._target(machine)
        target.clear_fault(name)
        await target.operator_after(name)  # a panel's key, a pendant's unlock: the kind's

    async def resolve(self, until: float, closed: float) -> None:
        """As an operator after fixing a machine (its fault window ``closed`` then): a few
        looks later, clear every alarm and release every held part (one held after a
        transfer once the arm is at rest); again if the looks after that raise more (a read
        that was out when the fault went), and while a step begun under the fault is still
        in flight (a block garbled by line noise fails only at its deadline)."""
        clock = current_clock()
        look = self.controller.options.poll_period
        rounds = 0
        while rounds < RESOLVE_ROUNDS and clock.now() < until:
            await clock.sleep(RESOLVE_LOOKS * look)
            alarms = self.journal.active_alarms()
            held = self.journal.parts(statuses=["held"])
            paused = self.controller.paused  # by an emergency stop: nothing else pauses a plan
            if not alarms and not held and not paused:
                if not self._under_fault(closed):
                    return
                continue
            rounds += 1
            for alarm in alarms:
                self.journal.clear_alarm(alarm.id, by="plan operator")
            if paused:
                # Released and its alarm cleared, the stop is resumed; refused while the
                # controller has not yet seen the release (asked again a few looks later).
                with contextlib.suppress(UsageError):
                    self.controller.resume()
            while held and self.cell.robot.moving:
                if clock.now() >= until:
                    return
                await clock.sleep(look)
            for part in held:
                self._release(part.id)
            await self._clear_machines()
            self.controller.poke()

    async def _clear_machines(self) -> None:
        """Each machine with no step in flight cleared at its panel (an error condition it
        keeps until someone does: a block garbled by line noise left the Dyna 2400 in ERROR).
        One with a step in flight is left alone: its readiness coming back would read as the
        step's end."""
        cell = self.cell
        busy = {s.machine for s in self.journal.steps() if s.state == "started"}
        for name in (cell.robot_name, *cell.mill_names):
            if name not in busy:
                await self._target(name).operator_clear()

    def _under_fault(self, closed: float) -> bool:
        """True while a step that began before ``closed`` is still in flight."""
        return any(s.state == "started" and s.started <= closed for s in self.journal.steps())

    def _release(self, part_id: str) -> None:
        cell = self.cell
        steps = self.journal.steps(part_id)
        if not steps:
            return  # held from the start (a held part of the running cell): stays held
        step = steps[-1]
        mills = {name: i for i, name in enumerate(cell.mill_names, start=1)}
        if step.kind == "transfer":
            source, target = step.program.split("_to_")
            if cell.gripper is not None and source in mills:
                cell.vise[mills[source]], cell.gripper = cell.gripper, None
            where = source
            if target in mills and cell.vise[mills[target]] is not None:
                where = target
            self.journal.release_part(part_id, location=where)
            return
        blank = cell.vise.get(mills.get(step.machine, 0))
        cut = cell.runs_per_part().get(blank, {}).get(step.machine, 0) if blank else 0
        self.journal.release_part(part_id, redo_step=not cut)
