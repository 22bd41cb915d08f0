"""The controller's command interface: what an operator surface may ask of a running cell.

:class:`OperatorCommands` is mixed into :class:`~cellctl.cell.controller.CellController`; the
control API (:mod:`cellctl.service`) calls these methods and nothing else of the controller::

    controller.pause()                               # steps in flight finish, none start
    await controller.set_service("cnc2", False)      # out of automatic service
    async with controller.manual("cnc2") as mill:    # the driver, for a manual function
        await mill.status()
    await controller.set_service("cnc2", True)       # prepared again, then dispatched to
    await controller.emergency_stop("guard opened")  # robot stopped, mills halted, alarm

``listeners`` are called (synchronously, cheaply) whenever the controller's state changed,
so a server can push updates instead of polling.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING, Any

from cellctl.errors import CellctlError, MachineInUse, UsageError

if TYPE_CHECKING:
    from cellctl.cell.config import CellConfig, MachineConfig
    from cellctl.cell.journal import Journal
    from cellctl.kinds.families import Mill, Robot

#: The journal's reason for a machine the operator took out of service: only the operator
#: returns it (clearing an alarm does not).
OPERATOR_OUT = "taken out by the operator"

#: Seconds an emergency stop waits for each machine to answer.
ESTOP_TIMEOUT = 10.0


class OperatorCommands:
    """Pause, resume, emergency stop, service and manual use of a machine (see module doc)."""

    if TYPE_CHECKING:
        config: CellConfig
        journal: Journal
        machines: dict[str, Any]
        robot: Robot | None
        mills: dict[str, Mill]
        _robot_task: asyncio.Task[None] | None
        _mill_tasks: dict[str, asyncio.Task[None]]

        def log(self, text: str) -> None: ...
        def wake(self) -> None: ...
        def alarm(self, machine: str, code: str, text: str) -> None: ...
        async def _prepare_robot(self) -> None: ...
        async def _prepare_mill(self, m: MachineConfig, *, force: bool) -> bool: ...

    paused: bool
    manual_use: set[str]
    listeners: list[Callable[[], None]]

    def _init_commands(self) -> None:
        self.paused = False
        self.manual_use = set()
        self.listeners = []

    def touch(self) -> None:
        """Tell every listener that the controller's state changed."""
        for listener in list(self.listeners):
            listener()

    def _known(self, name: str) -> None:
        if name not in self.machines or name == "plc":
            known = ", ".join(n for n in self.machines if n != "plc")
            raise UsageError(f"unknown machine {name!r} (known: {known})")

    def poke(self) -> None:
        """The operator changed the journal or the mailbox: look at it now, tell listeners."""
        self.wake()
        self.touch()

    def step_task(self, name: str) -> asyncio.Task[None] | None:
        """The step running on machine ``name``, if any."""
        task = self._robot_task if name == self.config.robot.name else self._mill_tasks.get(name)
        return task if task is not None and not task.done() else None

    def pause(self) -> None:
        """Start no new step; the steps in flight finish."""
        if not self.paused:
            self.paused = True
            self.log("paused by the operator: steps in flight finish, no new step starts")

    def resume(self) -> None:
        """Start dispatching again."""
        if self.paused:
            self.paused = False
            self.log("resumed by the operator")
            self.wake()

    async def set_service(self, name: str, in_service: bool, reason: str = "") -> str:
        """Take machine ``name`` out of automatic service, or return it (then it is prepared:
        a robot initialized, a mill initialized with its setup if it lost it)."""
        self._known(name)
        view = self.machines[name]
        if not in_service:
            why = f"{OPERATOR_OUT}: {reason}" if reason else OPERATOR_OUT
            self.journal.set_machine_service(name, False, why)
            view.in_service = False
            running = self.step_task(name)
            self.log(f"{name}: {why}" + (" (its step in flight finishes)" if running else ""))
            return f"{name} out of automatic service" + (
                "; its step in flight finishes first" if running else ""
            )
        if name in self.manual_use:
            raise MachineInUse(f"{name} is in use by a manual function: wait for it to end")
        self.journal.set_machine_service(name, True, "returned by the operator")
        view.in_service = True
        view.failures = 0
        if name == self.config.robot.name:
            await self._prepare_robot()
        else:
            await self._prepare_mill(self.config.machine(name), force=False)
        self.log(f"{name}: back in automatic service")
        self.wake()
        return f"{name} back in automatic service ({view.state})"

    @contextlib.asynccontextmanager
    async def manual(self, name: str) -> AsyncIterator[Any]:
        """The driver of machine ``name`` for a manual function: only while it is out of
        automatic service and no step runs on it. The monitor leaves it alone meanwhile."""
        self._known(name)
        view = self.machines[name]
        if view.in_service:
            raise MachineInUse(
                f"{name} is in automatic service: take it out first "
                f"(`cellctl machine {name} out`, or the console's service key)"
            )
        if self.step_task(name) is not None:
            raise MachineInUse(f"{name} is busy with {view.step or 'a step'}: wait for it to end")
        if name in self.manual_use:
            raise MachineInUse(f"{name} is in use by another manual function: wait for it")
        driver = self.robot if name == self.config.robot.name else self.mills.get(name)
        if driver is None:
            raise MachineInUse(f"{name} is not connected")
        self.manual_use.add(name)
        view.step = "manual"
        self.touch()
        try:
            yield driver
        finally:
            self.manual_use.discard(name)
            view.step = ""
            self.touch()

    @contextlib.asynccontextmanager
    async def observe(self, name: str) -> AsyncIterator[Any]:
        """The driver of ``name`` for a function that only reads it (status, DI/DO), in
        automatic service too. The robot's driver takes one transaction at a time, so a read
        slips in between the controller's own; a mill in the middle of a step answers from
        the host's state without touching its line."""
        self._known(name)
        if name == self.config.robot.name:
            if self.robot is None:
                raise MachineInUse(f"{name} is not connected")
            yield self.robot
            return
        mill = self.mills.get(name)
        if mill is None:
            raise MachineInUse(f"{name} is not connected")
        busy = self.step_task(name) is not None or name in self.manual_use
        yield _HostView(mill) if busy else mill

    async def emergency_stop(self, reason: str = "") -> str:
        """Stop the robot, halt the mills, raise an alarm, and pause the cell.

        Steps in flight are cut short: their parts are held for inspection (never lost).
        """
        self.paused = True
        text = "emergency stop" + (f": {reason}" if reason else " by the operator")
        tasks = [t for t in [self._robot_task, *self._mill_tasks.values()] if t and not t.done()]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, CellctlError, OSError):
                await task
        problems: list[str] = []
        if self.robot is not None and self.robot.running:
            try:
                async with asyncio.timeout(ESTOP_TIMEOUT):
                    await self.robot.stop()
            except (CellctlError, OSError, TimeoutError) as e:
                problems.append(f"robot stop failed: {e or 'no answer'}")
        for name, mill in self.mills.items():
            if mill.manual:
                continue  # in manual: nothing of ours runs there
            try:
                async with asyncio.timeout(ESTOP_TIMEOUT):
                    # The mill refuses END while a block runs: no more blocks go out, and
                    # the END follows the moment it is ready.
                    while mill.running and not (await mill.status()).ready:  # noqa: ASYNC110 - CTS is read, not signalled
                        await asyncio.sleep(0.05)
                    await mill.end()
            except TimeoutError:
                problems.append(
                    f"{name} still executes a block after {ESTOP_TIMEOUT:g} s: "
                    "stop it at the machine (END is refused while a block runs)"
                )
            except (CellctlError, OSError) as e:
                problems.append(f"{name} halt failed: {e}")
        self.alarm("cell", "estop", text + (f" ({'; '.join(problems)})" if problems else ""))
        self.log(f"{text}: cell paused; resume once the cause is dealt with")
        return text + ("; " + "; ".join(problems) if problems else "") + ": cell paused"


class _HostView:
    """A busy mill as the host sees it: its status from the host's state, no byte sent."""

    def __init__(self, mill: Mill) -> None:
        self.name = mill.name
        self.initialized = mill.initialized
        self._status = mill.host_status()

    async def status(self) -> Any:
        return self._status
