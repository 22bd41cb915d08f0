"""What the controller's parts need of the controller: narrow interfaces, one per need.

:class:`~cellctl.cell.controller.CellController` builds its parts (the monitor, recovery, the
robot's steps, the order bookkeeping) and hands each the interfaces below; the controller is
all of them, but no part imports it or reaches a private member::

    recovery = Recovery(world=controller, alarms=controller, links=controller)
    monitor = Monitor(world=controller, alarms=controller, plc=controller, recovery=recovery)
    robotsteps = RobotSteps(
        world=controller, alarms=controller, plc=controller, monitor=monitor, recovery=recovery
    )

- :class:`AlarmSink`: alarms (each fault once), the fail count, the log, and the nudges that
  wake the dispatch loop and tell the listeners.
- :class:`WorldModel`: M, what the controller knows (config, journal, options, machine views,
  the drivers, which machine runs a step or is in manual use, whether the cell stops).
- :class:`LinkOpener`: a machine's link opened again (its driver built from its config).
- :class:`PlcAccess`: the PLC's inputs, and the conveyor's pallet (overdue, or taken).
- :class:`CommandsHost`: what the operator's commands
  (:class:`~cellctl.cell.commands.OperatorCommands`, mixed into the controller) use of it: the
  type of their ``self``, so mypy checks the controller provides it.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from cellctl.cell.causes import Cause
    from cellctl.cell.config import CellConfig, MachineConfig
    from cellctl.cell.journal import Journal
    from cellctl.cell.model import ControllerOptions, MachineView
    from cellctl.cell.orders import OrderBox
    from cellctl.clock import Clock
    from cellctl.drivers.plc import ModbusPlc
    from cellctl.kinds.families import Mill, Robot


class AlarmSink(Protocol):
    """Where faults, failures and events go."""

    def alarm(self, machine: str, code: str, text: str) -> None:
        """Raise an alarm, unless ``machine`` has an active one with this ``code``."""

    def returned(self, machine: str, *codes: str) -> None:
        """The condition behind ``machine``'s open alarms with ``codes`` is gone."""

    def cause_alarm(self, cause: Cause) -> None:
        """The alarm of ``cause`` (only logged if its alarm was cleared while it was out)."""

    def failed(self, machine: str, code: str, text: str, *, alarm: bool = True) -> None:
        """A machine failed a step: alarm, and out of service after ``fail_limit`` in a row."""

    def succeeded(self, machine: str) -> None:
        """A machine did its step: its failures in a row start again from 0."""

    def log(self, text: str) -> None:
        """Note an event."""

    def wake(self) -> None:
        """Let the dispatch loop look again now (a step ended, a fault changed the plan)."""

    def touch(self) -> None:
        """Tell the listeners that the controller's state changed."""


class WorldModel(Protocol):
    """M, the world model: what the controller knows of the cell and its machines."""

    @property
    def clock(self) -> Clock:
        """What the cell reads the time from and waits on."""

    @property
    def config(self) -> CellConfig: ...
    @property
    def journal(self) -> Journal: ...
    @property
    def mailbox(self) -> OrderBox: ...
    @property
    def options(self) -> ControllerOptions: ...
    @property
    def machines(self) -> dict[str, MachineView]: ...
    @property
    def mills(self) -> dict[str, Mill]: ...
    @property
    def plc(self) -> ModbusPlc | None:
        """The PLC's driver (None until the controller connected)."""

    @property
    def manual_use(self) -> set[str]: ...
    @property
    def stopping(self) -> bool:
        """True once the cell was told to stop: no new step, no new recovery round."""

    robot: Robot | None
    #: What cancels the steps in flight when they are cancelled, for their held parts' notes
    #: ("an emergency stop", or the controller's own end when it is aborted).
    cancel_reason: str

    def robot_busy(self) -> bool:
        """True while a transfer runs."""

    def mill_busy(self, name: str) -> bool:
        """True while mill ``name`` machines a part."""

    def step_task(self, name: str) -> asyncio.Task[None] | None:
        """The step running on machine ``name``, if any."""

    def plc_view(self) -> MachineView:
        """The PLC's line in the live view."""

    def mill_index(self, name: str) -> int:
        """Mill ``name``'s number (1, 2, ...) in the PLC's wiring."""


class LinkOpener(Protocol):
    """A machine's driver, built from its config and its link opened."""

    async def open_robot(self) -> Robot: ...

    async def open_mill(self, m: MachineConfig) -> Mill: ...


class PlcAccess(Protocol):
    """The PLC as the parts see it."""

    async def read_inputs(self) -> dict[str, bool]:
        """Read the PLC's inputs now (kept as the controller's last look)."""

    def pallet_overdue(self) -> None:
        """Alarm if a requested pallet did not come within ``pallet_timeout``."""

    def pallet_taken(self) -> None:
        """The robot lifted a pallet off the conveyor: a request standing is served."""


class CommandsHost(WorldModel, AlarmSink, Protocol):
    """The controller as the operator's commands see it (the type of their ``self``)."""

    paused: bool
    listeners: list[Callable[[], None]]
    inputs: dict[str, bool]
    """The PLC's inputs at the monitor's last look."""

    async def prepare_robot(self) -> None:
        """Bring the robot to a known state (initialized), as on connecting."""

    async def prepare_mill(self, m: MachineConfig, *, force: bool) -> bool:
        """Bring mill ``m`` to a known state (its setup); True if it may take work."""

    def steps_in_flight(self) -> list[asyncio.Task[None]]:
        """The steps running now (the robot's transfer, each mill's machining)."""

    def halted(self, name: str) -> None:
        """Mill ``name`` was sent END by an emergency stop: initialized again on resume."""

    def resume_halted(self) -> None:
        """Initialize again the mills an emergency stop halted (the cell resumes)."""
