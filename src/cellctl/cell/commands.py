"""The controller's command interface: what an operator surface may ask of a running cell.

:class:`OperatorCommands` is mixed into :class:`~cellctl.cell.controller.CellController`; the
control API (:mod:`cellctl.service`) calls these methods and nothing else of the controller.
The commands' ``self`` is a :class:`~cellctl.cell.ports.CommandsHost`: all they use of the
controller, written once, and mypy checks the controller is one::

    controller.pause()                               # steps in flight finish, none start
    await controller.set_service("cnc2", False)      # out of automatic service
    async with controller.manual("cnc2") as mill:    # the driver, for a manual function
        await mill.status()
    await controller.set_service("cnc2", True)       # prepared again, then dispatched to
    await controller.emergency_stop("guard opened")  # robot stopped, mills halted, alarm

A manual function's driver reports its progress (a download's records, a mill's bytes and
blocks, its phase and estimate) to the machine's view as the controller's own steps do, so
the status shows it on every surface; :attr:`manual_steps` has each one's program and start.

``listeners`` are called (synchronously, cheaply) whenever the controller's state changed,
so a server can push updates instead of polling.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import inspect
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from cellctl.errors import CellctlError, MachineInUse, unknown_machine
from cellctl.kinds.families import RunProgress

if TYPE_CHECKING:
    from cellctl.cell.model import MachineView
    from cellctl.cell.ports import CommandsHost
    from cellctl.kinds.families import Mill

#: The journal's reason for a machine the operator took out of service: only the operator
#: returns it (clearing an alarm does not).
OPERATOR_OUT = "taken out by the operator"

#: Seconds an emergency stop waits for each machine to answer.
ESTOP_TIMEOUT = 10.0


@dataclass
class ManualStep:
    """A manual function running on a machine: when it began (s since the epoch) and the
    program it sends, once its driver was handed one."""

    started: float
    program: str | None = None


class OperatorCommands:
    """Pause, resume, emergency stop, service and manual use of a machine (see module doc)."""

    paused: bool
    manual_use: set[str]
    manual_steps: dict[str, ManualStep]
    """The manual functions running, by machine: the status' manual step."""
    listeners: list[Callable[[], None]]

    def _init_commands(self) -> None:
        self.paused = False
        self.manual_use = set()
        self.manual_steps = {}
        self.listeners = []

    def touch(self) -> None:
        """Tell every listener that the controller's state changed."""
        for listener in list(self.listeners):
            listener()

    def poke(self: CommandsHost) -> None:
        """The operator changed the journal or the mailbox: look at it now, tell listeners."""
        self.wake()
        self.touch()

    def pause(self: CommandsHost, by: str = "") -> None:
        """Start no new step; the steps in flight finish. ``by``: who asked, as the journal
        keeps it (``token:olga (operator)``; "": not known)."""
        if not self.paused:
            self.paused = True
            self.journal.note_controller("paused", by)
            # Who it was, as "resumed by" says it; "the operator" when nobody is known.
            who = by or "the operator"
            self.log(f"paused by {who}: steps in flight finish, no new step starts")

    def resume(self: CommandsHost, by: str = "") -> str:
        """Start dispatching again (the mills an emergency stop halted are initialized anew:
        their operators ready them at their panels first). Refused while an emergency stop
        is on, its button pressed or its alarm not cleared (MachineInUse: the stop holds the
        cell, exit code 6). ``by``: who asked, as for :meth:`pause`."""
        if not self.inputs.get("estop_ok", True):
            # The cell's state refuses it, not the request: the stop holds the cell until
            # the button is released and its alarm cleared (a reset must never start it).
            raise MachineInUse(f"the emergency stop is pressed: release it{_clear_estop(self)}")
        for a in self.journal.active_alarms():
            if a.code == "estop":
                raise MachineInUse(
                    f"the emergency stop's alarm {a.id} is not cleared: deal with its cause, "
                    f"clear it (`cellctl alarm clear {a.id}`), then resume"
                )
        if not self.paused:
            return "not paused: the cell runs"
        self.paused = False
        self.journal.note_controller("resumed", by)
        # Who it was (an engineer is no operator); "the operator" when nobody is known.
        self.log(f"resumed by {by or 'the operator'}")
        self.resume_halted()
        self.wake()
        return "resumed"

    async def set_service(self: CommandsHost, name: str, in_service: bool, reason: str = "") -> str:
        """Take machine ``name`` out of automatic service, or return it (then it is prepared:
        a robot initialized, a mill initialized with its setup if it lost it)."""
        view = _known(self.machines, name)
        out = self.journal.machines_out_of_service().get(name)
        if not in_service:
            # Out by the operator already: said again without a reason, the first one stays.
            if out is not None and out.startswith(OPERATOR_OUT) and not reason:
                return f"{name} is already out of automatic service ({out})"
            why = f"{OPERATOR_OUT}: {reason}" if reason else OPERATOR_OUT
            self.journal.set_machine_service(name, False, why)
            view.in_service = False
            running = self.step_task(name)
            self.log(f"{name}: {why}" + (" (its step in flight finishes)" if running else ""))
            return f"{name} out of automatic service" + (
                "; its step in flight finishes first" if running else ""
            )
        if view.in_service and out is None:
            return f"{name} is already in automatic service ({view.state})"
        if name in self.manual_use:
            raise MachineInUse(f"{name} is in use by a manual function: wait for it to end")
        self.journal.set_machine_service(name, True, "returned by the operator")
        view.in_service = True
        view.failures = 0
        # Its out-of-service alarm's condition is gone (the alarm stays open until cleared,
        # but no longer counts the machine down).
        self.returned(name, "out-of-service")
        if name == self.config.robot.name:
            await self.prepare_robot()
        else:
            await self.prepare_mill(self.config.machine(name), force=False)
        self.log(f"{name}: back in automatic service")
        self.wake()
        return f"{name} back in automatic service ({view.state})"

    @contextlib.asynccontextmanager
    async def manual(self: CommandsHost, name: str) -> AsyncIterator[Any]:
        """The driver of machine ``name`` for a manual function: only while it is out of
        automatic service and no step runs on it. The monitor leaves it alone meanwhile.
        What the function sends shows in the machine's view (its step and progress) until
        it ends, however it ends."""
        view = _known(self.machines, name)
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
        steps = cast(OperatorCommands, self).manual_steps
        step = ManualStep(started=self.clock.now())
        self.manual_use.add(name)
        steps[name] = step
        view.step = "manual"
        view.progress = None
        self.touch()

        def report(program: str | None, args: tuple[Any, ...]) -> None:
            if program is not None and step.program is None:
                step.program = program
            if _report(view, step, args):
                self.touch()

        try:
            yield _ManualDriver(driver, report)
        finally:
            self.manual_use.discard(name)
            steps.pop(name, None)
            view.step = ""
            view.progress = None
            self.touch()

    @contextlib.asynccontextmanager
    async def observe(self: CommandsHost, name: str) -> AsyncIterator[Any]:
        """The driver of ``name`` for a function that only reads it (status, DI/DO), in
        automatic service too. The robot's driver takes one transaction at a time, so a read
        slips in between the controller's own; a mill in the middle of a step answers from
        the host's state without touching its line."""
        _known(self.machines, name)
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

    async def emergency_stop(self: CommandsHost, reason: str = "", by: str = "") -> str:
        """Stop the robot, halt the mills, raise an alarm, and pause the cell (``by``: who
        asked, as for :meth:`pause`).

        Steps in flight are cut short: their parts are held for inspection (never lost).
        """
        was_paused, self.paused = self.paused, True
        text = "emergency stop" + (f": {reason}" if reason else " by the operator")
        # The alarm (and with it the cell's emergency-stop mode) at once: a mill may take the
        # rest of its block to halt, and the stop must show meanwhile.
        self.alarm("cell", "estop", text)
        if not was_paused:  # after the alarm: the shift report's record can wait a commit
            self.journal.note_controller("paused", by, text)
        self.log(f"{text}: cell paused; resume once the cause is dealt with")
        # What the held parts' notes say, for the steps this stop cancels (only those).
        previous, self.cancel_reason = self.cancel_reason, "an emergency stop"
        tasks = self.steps_in_flight()
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, CellctlError, OSError):
                await task
        self.cancel_reason = previous
        problems: list[str] = []
        robot = self.robot
        if robot is not None and robot.running:
            try:
                async with self.clock.timeout(ESTOP_TIMEOUT):
                    await robot.stop()
            except (CellctlError, OSError, TimeoutError) as e:
                problems.append(f"{robot.name}: stop failed: {e or 'no answer'}")
                self.alarm(robot.name, "estop", problems[-1])

        async def halt(name: str, mill: Mill) -> None:
            try:
                async with self.clock.timeout(ESTOP_TIMEOUT):
                    # The mill refuses END while a block runs: no more blocks go out, and
                    # the END follows the moment it is ready.
                    while mill.running and not (await mill.status()).ready:
                        await self.clock.sleep(0.05)
                    await mill.end()
                self.halted(name)
                return
            except TimeoutError:
                said = (
                    f"{name} still executes a block after {ESTOP_TIMEOUT:g} s: "
                    "stop it at the machine (END is refused while a block runs)"
                )
            except (CellctlError, OSError) as e:
                said = f"{name} halt failed: {e}"
            problems.append(said)
            self.alarm(name, "estop", said)
            # Not halted by END, its cut cut short all the same: set up again on resume, as
            # a halted mill is. The alarm returns to normal once a look finds it idle.
            self.halted(name)

        # Every mill at once: each waits out its own block (in manual, nothing of ours runs).
        await asyncio.gather(*(halt(n, m) for n, m in self.mills.items() if not m.manual))
        return text + ("; " + "; ".join(problems) if problems else "") + ": cell paused"


def _clear_estop(host: CommandsHost) -> str:
    """The rest of the way out of a pressed emergency stop, naming its open alarm(s):
    ", clear alarm 4 (`cellctl alarm clear 4`), then resume"."""
    ids = [a.id for a in host.journal.active_alarms() if a.code == "estop"]
    if not ids:  # not raised yet (the monitor's look raises it): said without its number
        return ", clear its alarm, then resume"
    which = "alarms " + ", ".join(map(str, ids)) if len(ids) > 1 else f"alarm {ids[0]}"
    commands = ", ".join(f"`cellctl alarm clear {i}`" for i in ids)
    return f", clear {which} ({commands}), then resume"


def _known(machines: dict[str, MachineView], name: str) -> MachineView:
    """Machine ``name``'s view; a name the cell does not know is refused, with the known."""
    if name not in machines or name == "plc":
        raise unknown_machine(name, [n for n in machines if n != "plc"])
    return machines[name]


def _report(view: MachineView, step: ManualStep, args: tuple[Any, ...]) -> bool:
    """Note a manual function's progress in ``view`` as the controller's own steps do: a
    mill's run (:class:`RunProgress`) in bytes and blocks, a robot's download (records done,
    of, bytes sent) in records. True when worth telling."""
    if len(args) == 1 and isinstance(args[0], RunProgress):
        return view.report_run(args[0], step.program, step.started)
    if len(args) == 3 and all(isinstance(a, int) for a in args):
        done, total, _sent = args
        return view.report_progress(
            done, total, "records", "downloading", program=step.program, since=step.started
        )
    return False


def _program_name(args: tuple[Any, ...]) -> str | None:
    """The name of the program a driver's call sends: a path's, or a program's own."""
    for arg in args:
        if isinstance(arg, Path):
            return arg.name
        name = getattr(arg, "name", None)
        if isinstance(name, str) and not isinstance(arg, str | bytes):
            return name
    return None


class _ManualDriver:
    """A driver lent to a manual function: every call given a ``progress`` callback also
    reports it (with the program the call sends) to ``report``; the rest is the driver's."""

    def __init__(self, driver: Any, report: Callable[[str | None, tuple[Any, ...]], None]) -> None:
        self._driver = driver
        self._report = report

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._driver, name)
        if not inspect.iscoroutinefunction(attr):
            return attr

        @functools.wraps(attr)
        async def call(*args: Any, **kwargs: Any) -> Any:
            given = kwargs.get("progress")
            if callable(given):
                program = _program_name(args)

                def progress(*values: Any) -> None:
                    given(*values)
                    self._report(program, values)

                kwargs["progress"] = progress
            return await attr(*args, **kwargs)

        return call


class _HostView:
    """A busy mill as the host sees it: its status from the host's state, no byte sent."""

    def __init__(self, mill: Mill) -> None:
        self.name = mill.name
        self.initialized = mill.initialized
        self._status = mill.host_status()

    async def status(self) -> Any:
        return self._status
