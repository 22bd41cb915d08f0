"""A whole cell in one process: the emulated cell, its controller, and an operator at the CLI.

This is the way to run a cell in one process -- for tests, benches and experiments::

    from cellctl.testing.rig import CellRig

    async with CellRig(tmp_path) as rig:          # robot, 2 mills, PLC on ptys and sockets
        rig.post("wax-robot-base", 2, "A")
        await rig.start_controller()              # CellController in this process
        await rig.wait_for(lambda: rig.order_state("A") == "done", "order A done")
        rig.switch_on("cnc2:stall")               # an emulator's fault switch
        await rig.wait_quiet()                    # no step in flight, the journal at rest
        await rig.switch_off("cnc2:stall")        # the operator fixes the machine ...
        await rig.operator_resolves()             # ... clears alarms, releases held parts

``CellRig(dir, cell_options=..., mill_options=...)`` writes short deadlines for tests
(:func:`fast_options`); ``CellRig(dir, deadlines="emulated")`` keeps the ones
``cellctl emulate cell`` writes, the deadlines a user gets.

On virtual time (a :class:`~cellctl.clock.VirtualLoop`: ``run_virtual``, or a test marked
``@pytest.mark.virtual``) the same rig runs the same cell on ``mem://`` lines and the PLC in
process, at the same time scale and with the same deadlines: every byte still takes its line
time and every cut its machining time, only the waiting is skipped::

    async with CellRig(tmp_path) as rig:          # on a virtual loop: links="mem" by itself
        ...

``rig.cli(...)`` runs the command line in a worker thread, as on real time: while it runs,
the virtual loop waits in real time (an executor job keeps its time from jumping) and its
time moves by the real time that passed. The command's own loop in that thread is virtual
too, from the cell's wall time: what it records is stamped on the cell's clock (:func:`cli`).

Waiting is always for a condition on the journal, the mailbox or the emulators, with a
deadline: never a bare sleep.

Layer: above everything (it drives the command line as an operator would); nothing in the
package imports it.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import threading
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from click.testing import CliRunner, Result

from cellctl.cell.config import load_cell
from cellctl.cell.controller import CellController, ControllerOptions
from cellctl.cell.journal import Journal, Step, open_journal
from cellctl.clock import VIRTUAL_ORIGIN, VirtualClock, VirtualLoop, current_clock
from cellctl.emulators.cell import EmulatedCell
from cellctl.emulators.memserve import serve_mem
from cellctl.errors import UsageError
from cellctl.kinds import registry
from cellctl.link.mem import MemPort, listen_mem
from cellctl.mailbox import Mailbox, open_mailbox
from cellctl.ui.cell_cli import apply_fault
from cellctl.ui.cli import main as cli_main

#: Machine time runs this many times faster than in the real cell.
TIME_SCALE = 1000.0

#: The mills, by the vise they own (the emulated cell's numbering).
MILL_INDEX = {"cnc1": 1, "cnc2": 2}

#: Deadlines short enough that a fault is found in well under a second of test time.
FAST_MILL_OPTIONS = {"setup_timeout": 1.5, "block_extra": 1.5, "ready_wait": 1.0}


def fast_options(**overrides: Any) -> dict[str, Any]:
    """``[cell]`` values for tests: short polls and deadlines."""
    values: dict[str, Any] = {
        "poll_period": 0.1,
        "transfer_timeout": 3.0,
        "interlock_timeout": 1.5,
        "pallet_timeout": 1.0,
        # Half the short poll (the default) is too little for a loaded test box: a slow
        # read would be told as a silent machine.
        "read_limit": 1.0,
    }
    values.update(overrides)
    return values


#: ``[plc]`` values for tests: the PLC in this process beside the controller, on a loaded box
#: (a 1 s answer, the default, is a LAN's; a test box's scheduling can take that long).
FAST_PLC_OPTIONS: dict[str, float] = {"timeout": 3.0}


class CellRig:
    """An :class:`EmulatedCell` in ``directory`` and, on demand, its controller."""

    def __init__(
        self,
        directory: Path,
        *,
        time_scale: float = TIME_SCALE,
        cell_options: dict[str, Any] | None = None,
        mill_options: dict[str, float] | None = None,
        plc_options: dict[str, float] | None = None,
        deadlines: Literal["fast", "emulated"] = "fast",
        links: Literal["real", "mem"] | None = None,
        template: Path | None = None,
    ) -> None:
        """``deadlines="fast"``: the tests' short deadlines (:func:`fast_options`), then
        ``cell_options`` and ``mill_options`` over them; ``"emulated"``: only those given
        over what ``cellctl emulate cell`` writes. ``plc_options``: ``[plc]`` values
        (``timeout``, ``poll``), over :data:`FAST_PLC_OPTIONS` for fast deadlines.
        ``links``: the machines on ptys and sockets ("real") or in this loop ("mem"); by
        default "mem" on a virtual loop (made in it), where real links cannot go, else
        "real". ``template``: the cell directory to emulate (default: the example cell)."""
        self.directory = directory
        clock = current_clock()
        if isinstance(clock, VirtualClock):
            if links == "real":
                raise UsageError(
                    "a CellRig on virtual time joins its machines through mem:// links: "
                    "real ptys and sockets would be answered after time jumped past"
                )
            self.cell = EmulatedCell(
                clock=scaled_clock(clock, time_scale), links="mem", template=template
            )
        else:
            self.cell = EmulatedCell(
                time_scale=time_scale, links=links or "real", template=template
            )
        fast = deadlines == "fast"
        self.cell_options = fast_options(**(cell_options or {})) if fast else (cell_options or {})
        self.mill_options = {**(FAST_MILL_OPTIONS if fast else {}), **(mill_options or {})}
        self.plc_options = {**(FAST_PLC_OPTIONS if fast else {}), **(plc_options or {})}
        self.controller: CellController | None = None
        self.stop_event = asyncio.Event()
        self._run_task: asyncio.Task[None] | None = None
        self.journal: Journal
        self.mailbox: Mailbox

    async def __aenter__(self) -> CellRig:
        toml = await self.cell.start(self.directory)
        write_cell_options(toml, self.cell_options, self.mill_options, self.plc_options)
        self.journal = open_journal(self.directory)
        self.mailbox = open_mailbox(self.directory)
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            if self._run_task is not None and not self._run_task.done():
                self._run_task.cancel()
                with contextlib.suppress(BaseException):
                    await self._run_task
            if self.controller is not None:
                with contextlib.suppress(Exception):
                    await self.controller.close()
        finally:
            self.journal.close()
            self.mailbox.close()
            await self.cell.close()

    # -- the controller ---------------------------------------------------------------------

    async def start_controller(self, **overrides: Any) -> CellController:
        """Connect a controller to the cell and run it in a task (until :meth:`stop_controller`)."""
        config = load_cell(self.directory)
        options = ControllerOptions.from_config(config, **overrides)
        controller = CellController(
            config, open_journal(self.directory), open_mailbox(self.directory), options=options
        )
        await controller.connect()
        self.controller = controller
        self.stop_event = asyncio.Event()
        self._run_task = asyncio.create_task(controller.run(self.stop_event))
        return controller

    async def stop_controller(self, timeout: float = 30.0) -> None:
        """Stop the controller as SIGINT does (steps in flight finish) and close its links."""
        assert self.controller is not None and self._run_task is not None
        self.stop_event.set()
        async with asyncio.timeout(timeout):
            await self._run_task
        await self.controller.close()
        self.controller = None
        self._run_task = None

    def check_running(self) -> None:
        """Fail at once if the controller's loop died."""
        task = self._run_task
        if task is not None and task.done():
            task.result()  # raises what killed it
            raise AssertionError("the controller stopped on its own")

    # -- waiting -----------------------------------------------------------------------------

    async def wait_for(self, condition: Callable[[], Any], what: str, timeout: float = 30.0) -> Any:
        """Poll ``condition`` until it returns something true; fail after ``timeout``."""
        clock = current_clock()
        deadline = clock.monotonic() + timeout
        while True:
            value = condition()
            if value:
                return value
            self.check_running()
            if clock.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for: {what}\n{self.describe()}")
            await clock.sleep(0.02)

    def finished_steps(self, kind: str | None = None) -> int:
        return sum(
            1
            for s in self.journal.steps()
            if s.state == "finished" and (kind is None or s.kind == kind)
        )

    def open_steps(self, kind: str) -> list[Any]:
        return [s for s in self.journal.open_steps() if s.kind == kind]

    def order_state(self, order_id: str) -> str:
        return self.mailbox.get_order(order_id).state

    def orders_settled(self) -> bool:
        """Every order done, failed, or with all its unfinished parts held."""
        for order in self.mailbox.orders():
            if order.state in ("done", "failed"):
                continue
            parts = self.journal.parts(order_id=order.id)
            if not parts or any(p.status in ("waiting", "active") for p in parts):
                return False
        return True

    def quiet_span(self) -> float:
        """Seconds of nothing new after which the cell is at rest: the longest deadline that
        can still fire with no step in flight (a setup's ``setup_timeout`` and the look that
        tells it, a pallet's ``pallet_timeout``, a silent read's ``read_limit``), plus a poll
        period, all from the cell's own cell.toml."""
        config = load_cell(self.directory)
        options = ControllerOptions.from_config(config)
        setups = [
            float(getattr(registry.kind(m.kind).checked_options(m.options), "setup_timeout", 0))
            for m in config.mills
        ]
        longest = max(options.pallet_timeout, options.read_limit, *setups)
        return longest + 2 * options.poll_period

    def _journal_state(self) -> tuple[object, ...]:
        steps = tuple((s.id, s.state) for s in self.journal.steps())
        alarms = tuple(a.id for a in self.journal.alarms())
        parts = tuple((p.id, p.status, p.location) for p in self.journal.parts())
        return steps, alarms, parts

    async def wait_quiet(
        self, span: float | None = None, what: str = "the cell at rest", timeout: float = 60.0
    ) -> None:
        """Wait until no step is in flight and the journal (steps, alarms, parts) has not
        changed for ``span`` s (default :meth:`quiet_span`): whatever a fault still had to
        raise has been raised. Fails after ``timeout``."""
        span = self.quiet_span() if span is None else span
        clock = current_clock()
        state = self._journal_state()
        since = clock.monotonic()

        def at_rest() -> bool:
            nonlocal state, since
            now = self._journal_state()
            if now != state or self.journal.open_steps():
                state, since = now, clock.monotonic()
                return False
            return clock.monotonic() - since >= span

        await self.wait_for(at_rest, f"{what} ({span:g} s with nothing new)", timeout=timeout)

    def all_done(self) -> bool:
        return all(o.state == "done" for o in self.mailbox.orders())

    def held_parts(self) -> list[Any]:
        return self.journal.parts(statuses=["held"])

    def alarms(self, machine: str | None = None, code: str | None = None) -> list[Any]:
        return [
            a
            for a in self.journal.active_alarms()
            if (machine is None or a.machine == machine) and (code is None or a.code == code)
        ]

    def reports(self, kind: str) -> list[Any]:
        return [r for r in self.mailbox.reports() if r.kind == kind]

    def describe(self) -> str:
        lines = ["orders:"]
        lines += [f"  {o.id} {o.state} {o.note}" for o in self.mailbox.orders()]
        lines.append("parts:")
        lines += [
            f"  {p.id} {p.location} r{p.route_index} {p.status} {p.note}"
            for p in self.journal.parts()
        ]
        lines.append("steps:")
        lines += [
            f"  {s.id} {s.part_id} {s.kind} {s.machine} {s.program} {s.state} {s.outcome[:90]}"
            for s in self.journal.steps()
        ]
        lines.append("alarms:")
        lines += [
            f"  {a.id} {a.machine} {a.code} {a.state} {a.text}" for a in self.journal.alarms()
        ]
        if self.controller is not None:
            lines.append("machines:")
            lines += [
                f"  {v.name} {v.state} in_service={v.in_service} failures={v.failures}"
                for v in self.controller.machines.values()
            ]
            lines.append("events:")
            lines += [f"  {e.text}" for e in self.controller.events[-25:]]
        lines.append(f"runs per part: {self.cell.runs_per_part()}")
        return "\n".join(lines)

    # -- orders and the operator -------------------------------------------------------------

    def post(self, part_type: str, qty: int, order_id: str) -> None:
        self.mailbox.post_order(part_type, qty, order_id=order_id)

    async def cli(self, *args: str) -> Result:
        """Run ``cellctl --cell DIR ARGS`` as the operator would (in a worker thread)."""
        return await cli(self.directory, *args)

    async def clear_alarms(self) -> list[int]:
        """The operator clears every active alarm with ``cellctl alarm clear ID``."""
        cleared = []
        for alarm in self.journal.active_alarms():
            result = await self.cli("alarm", "clear", str(alarm.id))
            assert result.exit_code == 0, result.output
            cleared.append(alarm.id)
        return cleared

    # -- faults ------------------------------------------------------------------------------

    def switch_on(self, fault: str) -> None:
        """Switch an emulator's fault on: ``MACHINE:NAME[=ARG]`` as ``cellctl emulate cell
        --fault`` takes it (``cnc2:stall``, ``plc:stuck-door=2``)."""
        apply_fault(self.cell, fault)

    async def switch_off(self, fault: str) -> None:
        """The operator fixes the machine: the fault off, and what its panel needs after it
        (the emulator's ``operator_after``: NEXT after a setup stop, the link mode selected
        again after a lost READY, a pendant's unlock)."""
        machine, _, rest = fault.partition(":")
        name = rest.partition("=")[0]
        if machine == "robot":
            target = self.cell.robot
        elif machine == "plc":
            target = self.cell.plc
        else:
            target = self.cell.mills[machine]
        target.clear_fault(name)
        await target.operator_after(name)

    @contextlib.asynccontextmanager
    async def connections_dropped(self, mill: str) -> AsyncIterator[list[float]]:
        """While inside, ``mill``'s line (``mem://`` links only) is a device server that
        takes each connection and closes it at once, as ser2net does for a moment after a
        drop ("Port already in use"); the mill's emulator is off the line (its connection
        cut on entering) and serves it again on leaving. Yields the times
        (``monotonic()`` of the running clock) of the connections taken, as they come."""
        if self.cell.links != "mem":
            raise UsageError("connections_dropped takes a cell on mem:// links")
        clock = current_clock()
        name = f"{self.cell.mem_prefix}{mill}"
        line = self.cell.line_of(mill)
        taken: list[float] = []

        def drop(port: MemPort) -> None:
            taken.append(clock.monotonic())
            port.drop()

        await self.cell.servers[mill].close()
        listener = listen_mem(name, line, drop)
        try:
            yield taken
        finally:
            listener.close()
            self.cell.servers[mill] = await serve_mem(
                self.cell.mills[mill], line, name=name, pacing=self.cell.pacing
            )

    def physical_part(self, mill: str) -> str | None:
        """The physical part in ``mill``'s vise (the emulated cell's record)."""
        return self.cell.vise[self.cell.mill_names.index(mill) + 1]

    async def operator_resolves(self) -> None:
        """The operator clears every alarm and releases each held part where it physically
        is, after looking at it (``cellctl alarm clear``, ``cellctl part release``); and
        resumes a cell an emergency stop paused (``cellctl resume``)."""
        estop = any(a.code == "estop" for a in self.journal.active_alarms())
        await self.clear_alarms()
        controller = self.controller
        if estop and controller is not None:
            # Refused until the controller has seen the button released: looked at again.
            await self.wait_for(lambda: controller.inputs.get("estop_ok", True), "the release seen")
            controller.resume()  # what `cellctl resume` asks the running controller
        for part in self.held_parts():
            step = self.journal.steps(part.id)[-1]
            if step.kind == "transfer":
                where = await where_transferred(self.cell, self.journal, step)
                result = await self.cli("part", "release", part.id, "--at", where)
            else:
                # Inspect the part in the vise: cut already (the mill's log says so), or not.
                blank = self.physical_part(step.machine)
                assert blank is not None, f"{part.id} should be in {step.machine}'s vise"
                cut = self.cell.runs_per_part().get(blank, {}).get(step.machine, 0)
                args = ["part", "release", part.id] + ([] if cut else ["--redo"])
                result = await self.cli(*args)
            assert result.exit_code == 0, result.output

    def cut_twice(self) -> dict[str, dict[str, int]]:
        """Physical parts some mill cut more than once (from the mills' execution logs)."""
        return {
            p: r for p, r in self.cell.runs_per_part().items() if any(n > 1 for n in r.values())
        }


async def where_transferred(
    cell: EmulatedCell, journal: Journal, step: Step, timeout: float = 30.0
) -> str:
    """Where the operator finds the part of a transfer ``step`` that did not end (the
    ``--at`` of ``cellctl part release``), from the emulated cell's physical state.

    The operator waits for the arm to stop; a part still in the gripper (a cycle stopped
    mid-way) goes back where it came from, by hand; else it is where the arm left it: at the
    target (a vise holds it, or the outfeed has one more than the parts done), or still at
    the source.
    """
    clock = current_clock()
    deadline = clock.monotonic() + timeout
    while cell.robot.running:
        if clock.monotonic() > deadline:
            raise AssertionError(f"the arm still moving after {timeout:g} s ({step.program})")
        await clock.sleep(0.01)
    source, target = step.program.split("_to_")
    if cell.gripper is not None:
        if source in MILL_INDEX:
            cell.vise[MILL_INDEX[source]], cell.gripper = cell.gripper, None
        else:
            assert cell.pallet_part is None, f"{cell.gripper} in the gripper, a pallet waiting"
            cell.pallet_part, cell.gripper = cell.gripper, None
        return source
    if target in MILL_INDEX:
        return target if cell.vise[MILL_INDEX[target]] is not None else source
    made = sum(p.status == "done" for p in journal.parts())
    return "out" if len(cell.outfeed) > made else source


async def cli(directory: Path, *args: str) -> Result:
    """``cellctl --cell DIRECTORY ARGS`` through click, in a worker thread (own event loop).

    Called on virtual time, the command's loop in that thread is virtual too, started at the
    caller's wall time (:class:`_CommandLoops`): what it records (an alarm cleared, a part
    released) is stamped at the moment the operator acted on the cell's clock, as on real
    time, not at the wall clock's, which a virtual run is far ahead of.
    """
    clock = current_clock()
    virtual = isinstance(clock, VirtualClock)
    if virtual:
        _CommandLoops.install()

    def invoke() -> Result:
        if virtual:
            _command_thread.start = clock.now()
        try:
            return CliRunner().invoke(cli_main, ["--cell", str(directory), *args])
        finally:
            _command_thread.start = None

    return await asyncio.to_thread(invoke)


# What a command run by :func:`cli` in this thread starts its virtual loop at (None: real).
_command_thread = threading.local()


class _CommandLoops(asyncio.AbstractEventLoopPolicy):
    """The event loop policy while a rig on virtual time runs commands: a command's loop
    (``asyncio.run`` in :func:`cli`'s worker thread) is a :class:`VirtualLoop` at the
    caller's wall time, taking real I/O; everything else is the policy it wraps."""

    def __init__(self, base: asyncio.AbstractEventLoopPolicy) -> None:
        self.base = base

    @classmethod
    def install(cls) -> None:
        policy = asyncio.get_event_loop_policy()
        if not isinstance(policy, cls):
            asyncio.set_event_loop_policy(cls(policy))

    def new_event_loop(self) -> asyncio.AbstractEventLoop:
        start = getattr(_command_thread, "start", None)
        if start is None:
            return self.base.new_event_loop()
        return VirtualLoop(start=start, allow_real_io=True)

    def get_event_loop(self) -> asyncio.AbstractEventLoop:
        return self.base.get_event_loop()

    def set_event_loop(self, loop: asyncio.AbstractEventLoop | None) -> None:
        self.base.set_event_loop(loop)


def scaled_clock(clock: VirtualClock, time_scale: float) -> VirtualClock:
    """``clock``'s virtual time (the same loop, the same wall time) with machines
    ``time_scale`` times faster than life: what the rig's emulators run on."""
    if time_scale == clock.time_scale:
        return clock
    wall_start = clock.now() - clock.monotonic() + VIRTUAL_ORIGIN
    return VirtualClock(clock.loop, wall_start, time_scale)


def write_cell_options(
    toml: Path,
    cell_options: dict[str, Any],
    mill_options: dict[str, float],
    plc_options: dict[str, float] | None = None,
) -> None:
    """Set ``[cell]`` values, every mill's options and ``[plc]`` values in the emulated
    cell's cell.toml."""
    text = toml.read_text(encoding="utf-8")
    for key, value in (plc_options or {}).items():
        start = text.index("[plc]\n") + len("[plc]\n")
        end = text.find("\n[", start) + 1 or len(text)
        section = re.sub(rf"^{key}\s*=.*\n", "", text[start:end], flags=re.MULTILINE)
        text = text[:start] + f"{key} = {value:g}\n" + section + text[end:]
    for key, value in cell_options.items():
        line = f"{key} = {_toml_value(value)}"
        pattern = re.compile(rf"^{key}\s*=.*$", re.MULTILINE)
        if pattern.search(text):
            text = pattern.sub(line, text, count=1)
        else:
            text = text.replace("[cell]\n", f"[cell]\n{line}\n", 1)
    for key, value in mill_options.items():
        text = re.sub(rf"^{key}\s*=.*$", f"{key} = {value:g}", text, flags=re.MULTILINE)
    toml.write_text(text, encoding="utf-8")


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return str(value)
