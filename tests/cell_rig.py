"""The emulated cell and its controller in the test process, and an operator at the CLI.

::

    async with CellRig(tmp_path) as rig:          # robot, 2 mills, PLC on ptys and sockets
        rig.post("wax-robot-base", 2, "A")
        await rig.start_controller()              # CellController in this process
        await rig.wait_for(lambda: rig.order_state("A") == "done", "order A done")
        rig.cli("alarm", "clear", "3")             # what the operator types

Waiting is always for a condition on the journal, the mailbox or the emulators, with a
deadline: never a bare sleep.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any

from click.testing import CliRunner, Result

from cellctl.cell.config import load_cell
from cellctl.cell.controller import CellController, ControllerOptions
from cellctl.cell.journal import Journal, open_journal
from cellctl.emulators.cell import EmulatedCell
from cellctl.mailbox import Mailbox, open_mailbox
from cellctl.ui.cli import main as cli_main

#: Machine time runs this many times faster than in the real cell.
TIME_SCALE = 1000.0

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


class CellRig:
    """An :class:`EmulatedCell` in ``directory`` and, on demand, its controller."""

    def __init__(
        self,
        directory: Path,
        *,
        time_scale: float = TIME_SCALE,
        cell_options: dict[str, Any] | None = None,
        mill_options: dict[str, float] | None = None,
    ) -> None:
        self.directory = directory
        self.cell = EmulatedCell(time_scale=time_scale)
        self.cell_options = fast_options(**(cell_options or {}))
        self.mill_options = {**FAST_MILL_OPTIONS, **(mill_options or {})}
        self.controller: CellController | None = None
        self.stop_event = asyncio.Event()
        self._run_task: asyncio.Task[None] | None = None
        self.journal: Journal
        self.mailbox: Mailbox

    async def __aenter__(self) -> CellRig:
        toml = await self.cell.start(self.directory)
        write_cell_options(toml, self.cell_options, self.mill_options)
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
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            value = condition()
            if value:
                return value
            self.check_running()
            if loop.time() > deadline:
                raise AssertionError(f"timed out waiting for: {what}\n{self.describe()}")
            await asyncio.sleep(0.02)

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

    def cut_twice(self) -> dict[str, dict[str, int]]:
        """Physical parts some mill cut more than once (from the mills' execution logs)."""
        return {
            p: r for p, r in self.cell.runs_per_part().items() if any(n > 1 for n in r.values())
        }


async def cli(directory: Path, *args: str) -> Result:
    """``cellctl --cell DIRECTORY ARGS`` through click, in a worker thread (own event loop)."""

    def invoke() -> Result:
        return CliRunner().invoke(cli_main, ["--cell", str(directory), *args])

    return await asyncio.to_thread(invoke)


def write_cell_options(
    toml: Path, cell_options: dict[str, Any], mill_options: dict[str, float]
) -> None:
    """Set ``[cell]`` values and every mill's options in the emulated cell's cell.toml."""
    text = toml.read_text(encoding="utf-8")
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
