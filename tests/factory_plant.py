"""The factory of tests/test_factory.py and tests/test_factory_edges.py: a real Mosquitto,
emulated cells in the test process (so the mills' own logs can be read), and each cell's
``cellctl run`` and ``cellctl factory run`` as subprocesses whose output goes to log files
shown on failure; the batch, the deadlines and the one check that every order's parts were
made once."""

from __future__ import annotations

import asyncio
import os
import signal
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from cellctl.cell.config import load_cell
from cellctl.cell.journal import Journal, open_journal
from cellctl.emulators.cell import EmulatedCell
from cellctl.factory.config import load_factory
from cellctl.factory.emulated import EmulatedFactory
from cellctl.factory.store import DONE, FactoryStore
from cellctl.mailbox import CANCELLED, Mailbox, open_mailbox
from cellctl.testing.rig import MILL_INDEX, TIME_SCALE, cli, where_transferred, write_cell_options

from .conftest import CELLCTL

PART_TYPES = ("wax-robot-base", "wax-toy-mill-table")
#: The batch: 30 orders of both types, every fifth for two parts; the last ten are submitted
#: while the fault is on (an order comes in while a cell, the broker or the factory is away).
BATCH = [(f"F{n:02d}", PART_TYPES[n % 2], 2 if n % 5 == 0 else 1) for n in range(1, 31)]
FIRST, DURING = BATCH[:20], BATCH[20:]
#: Deadline of one wait for the plant (the whole batch takes about 12 s on an idle box).
WAIT_S = 60.0
#: Deadline of one operator command.
CLI_S = 30.0
#: A pallet asked for comes within milliseconds here: one that does not come is an alarm
#: after 2 s, not after the example cell's 60 (a failure then says so within the deadlines).
CELL_OPTIONS = {"pallet_timeout": 2.0, "read_limit": 2.0}
#: The cells' emulators share this process with the plant's own waits on a box the suite
#: keeps busy: a PLC or robot answer can take over the cell's 1 or 2 s, which fails a step
#: for a reason no factory test is about (tests/test_cell_faults.py has the silent machines).
LOADED_S = 5.0


class Plant:
    """An :class:`EmulatedFactory` in this process; its cells' controllers and the factory
    controller as ``cellctl`` subprocesses, started and killed by name (``cell2``, ``factory``).
    """

    def __init__(
        self, directory: Path, *, cells: int = 3, templates: Sequence[Path | None] = ()
    ) -> None:
        self.directory = directory
        self.emulated = EmulatedFactory(
            directory,
            cells=cells,
            time_scale=TIME_SCALE,
            poll_period=0.1,
            factory_poll=0.1,
            templates=templates,
        )
        self.logs = directory / "logs"
        self.procs: dict[str, asyncio.subprocess.Process] = {}
        self.store: FactoryStore
        self.journals: dict[str, Journal] = {}
        self.mailboxes: dict[str, Mailbox] = {}

    @property
    def names(self) -> list[str]:
        return self.emulated.names

    def cell(self, name: str) -> EmulatedCell:
        return self.emulated.cells[self.names.index(name)]

    def cell_dir(self, name: str) -> Path:
        return self.directory / name

    async def __aenter__(self) -> Plant:
        await self.emulated.start()
        try:
            for name in self.names:
                toml = self.cell_dir(name) / "cell.toml"
                write_cell_options(toml, CELL_OPTIONS, {}, {"timeout": LOADED_S})
                if "[machines.robot.options]" not in toml.read_text():
                    with toml.open("a") as f:
                        f.write(f"\n[machines.robot.options]\nreply_timeout = {LOADED_S}\n")
            self.logs.mkdir()
            self.store = FactoryStore(load_factory(self.directory).state_path)
            for name in self.names:
                self.journals[name] = open_journal(self.cell_dir(name))
                self.mailboxes[name] = open_mailbox(self.cell_dir(name))
        except BaseException:
            await self.emulated.close()
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        try:
            for name in list(self.procs):
                await self.stop(name)
        finally:
            for journal in self.journals.values():
                journal.close()
            for mailbox in self.mailboxes.values():
                mailbox.close()
            self.store.close()
            await self.emulated.close()

    # -- the controllers ---------------------------------------------------------------------

    async def start(self, name: str, *more: str) -> asyncio.subprocess.Process:
        """Start ``cellctl run`` of cell ``name``, or ``cellctl factory run`` for "factory"
        (``more``: options of ``run``, e.g. ``--until-idle``)."""
        assert name not in self.procs, f"{name} is running"
        if name == "factory":
            args = ["factory", "--dir", str(self.directory), "run", "--no-live", *more]
        else:
            args = ["--cell", str(self.cell_dir(name)), "run", "--no-live", *more]
        with (self.logs / f"{name}.log").open("ab") as log:
            log.write(f"---- started {' '.join(args)}\n".encode())
            log.flush()
            proc = await asyncio.create_subprocess_exec(
                *CELLCTL,
                *args,
                stdin=asyncio.subprocess.DEVNULL,
                stdout=log,
                stderr=asyncio.subprocess.STDOUT,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        self.procs[name] = proc
        return proc

    async def kill(self, name: str) -> None:
        """kill -9 ``name``'s process."""
        proc = self.procs.pop(name)
        assert proc.returncode is None, f"{name} had already exited\n{self.describe()}"
        proc.send_signal(signal.SIGKILL)
        await proc.wait()

    async def stop(self, name: str) -> None:
        """SIGTERM ``name``'s process (killed if it does not exit within 15 s)."""
        proc = self.procs.pop(name)
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
        try:
            async with asyncio.timeout(15):
                await proc.wait()
        except TimeoutError:
            proc.kill()
            await proc.wait()

    def part_types(self, name: str) -> set[str]:
        """What cell ``name`` makes: the part types of its cell.toml."""
        return set(load_cell(self.cell_dir(name)).parts)

    async def start_all(self) -> None:
        """Every cell's controller and the factory's; returns once the factory knows what
        each cell makes."""
        for name in [*self.names, "factory"]:
            await self.start(name)
        makes = {name: self.part_types(name) for name in self.names}

        def heard() -> bool:
            # One read: of two, the first could miss a cell the second finds with no state yet.
            cells = self.store.cells()
            return set(cells) == set(self.names) and all(
                makes[name] <= set(c.part_types) and c.status == "online"
                for name, c in cells.items()
            )

        await self.wait_for(heard, "the factory hears every cell online with its part types")

    # -- orders --------------------------------------------------------------------------------

    def submit(self, batch: list[tuple[str, str, int]]) -> None:
        """What ``cellctl factory submit`` does, for each order of ``batch``."""
        for oid, part_type, qty in batch:
            _, new = self.store.submit(part_type, qty, priority=0, order_id=oid)
            assert new

    def done(self) -> set[str]:
        return {o.id for o in self.store.orders([DONE])}

    def cells_done(self) -> set[str]:
        """Orders some cell's own mailbox says are done."""
        return {o.id for mb in self.mailboxes.values() for o in mb.orders() if o.state == DONE}

    def cutting(self) -> str | None:
        """A cell whose journal has a cut in flight that its emulated mill is running on a
        part (and more work to do after it), or None."""
        for name, journal in self.journals.items():
            for step in journal.open_steps():
                mill = self.cell(name).mills.get(step.machine)
                if step.kind != "machine" or mill is None or not mill.executing:
                    continue
                if self.cell(name).vise[MILL_INDEX[step.machine]] is None:
                    continue
                if len(self.journals[name].parts(statuses=["waiting"])) > 0:
                    return name
        return None

    def held(self) -> dict[str, list[str]]:
        return {
            name: [p.id for p in j.parts(statuses=["held"])]
            for name, j in self.journals.items()
            if j.parts(statuses=["held"])
        }

    def reports_caught_up(self) -> bool:
        """The factory has every report each cell's mailbox made (seq 1, 2, 3 ... of its
        epoch), and no other."""
        seen = self.store.cells()
        for name, mailbox in self.mailboxes.items():
            reports = mailbox.reports()
            if not reports:
                continue
            if name not in seen or seen[name].epoch != mailbox.epoch:
                return False
            if seen[name].seq != reports[-1].seq:
                return False
        return True

    # -- waiting -------------------------------------------------------------------------------

    async def wait_for(
        self, condition: Callable[[], Any], what: str, timeout: float = WAIT_S
    ) -> Any:
        """Poll ``condition`` until it is true; fail at once if a controller died, or with
        the plant's state after ``timeout``."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            value = condition()
            if value:
                return value
            for name, proc in self.procs.items():
                if proc.returncode is not None:
                    raise AssertionError(
                        f"{name} exited ({proc.returncode}) while waiting for: {what}\n"
                        + self.describe()
                    )
            if loop.time() > deadline:
                raise AssertionError(
                    f"timed out after {timeout:g} s waiting for: {what}\n{self.describe()}"
                )
            await asyncio.sleep(0.05)

    async def finish(self, *, operator: bool = False) -> None:
        """Until every order is done and the factory has every report. With ``operator``
        the operator inspects each held part as it comes; without, a held part fails."""
        for _ in range(10):
            await self.wait_for(
                lambda: (
                    (len(self.done()) == len(BATCH) and self.reports_caught_up()) or self.held()
                ),
                "every order done, the factory up to date with every cell's reports",
            )
            held = self.held()
            if not held:
                return
            assert operator, f"parts held: {held}\n{self.describe()}"
            for name in held:
                await self.operator_inspects(name)
        raise AssertionError(f"still parts held after 10 inspections\n{self.describe()}")

    async def operator_inspects(self, name: str) -> None:
        """The operator clears cell ``name``'s alarms, looks at each held part in the cell
        (the emulators' physical state) and releases it as it is: a part in a vise whose
        mill's log shows its cut counts as cut; a transfer's part is where the robot left it."""
        cell, journal, cell_dir = self.cell(name), self.journals[name], self.cell_dir(name)

        async def operator(*args: str) -> None:
            try:
                async with asyncio.timeout(CLI_S):
                    result = await cli(cell_dir, *args)
            except TimeoutError:
                raise AssertionError(
                    f"cellctl {' '.join(args)}: no answer\n{self.describe()}"
                ) from None
            assert result.exit_code == 0, f"{args}: {result.output}\n{self.describe()}"

        for alarm in journal.active_alarms():
            await operator("alarm", "clear", str(alarm.id))
        for part in journal.parts(statuses=["held"]):
            step = journal.steps(part.id)[-1]
            if step.kind == "transfer":
                where = await where_transferred(cell, journal, step)
                await operator("part", "release", part.id, "--at", where)
            else:
                blank = cell.vise[MILL_INDEX[step.machine]]
                assert blank is not None, (
                    f"{part.id}: {step.machine}'s vise empty\n{self.describe()}"
                )
                cut = cell.runs_per_part().get(blank, {}).get(step.machine, 0)
                await operator("part", "release", part.id, *([] if cut else ["--redo"]))

    def _physical(self, name: str) -> list[str]:
        """What the emulators of cell ``name`` say: where the parts are, the PLC's signals."""
        cell = self.cell(name)
        plc = cell.plc
        on = [n for n, v in {**plc.inputs, **plc.coils}.items() if v]
        return [
            f"  mills cut: {cell.runs_per_part()}",
            f"  pallet {cell.pallet_part} gripper {cell.gripper} vises {cell.vise}"
            f" outfeed {cell.outfeed}",
            f"  plc on: {on} pallets delivered {plc.pallets_delivered}"
            f" timers {sorted(plc._timers)}",
            "  mills: " + ", ".join(f"{m}: {_shown(mill)}" for m, mill in cell.mills.items()),
            f"  robot: {_shown(cell.robot)}",
        ]

    def describe(self) -> str:
        """The factory's orders and events, each cell's open work, the processes' logs."""
        lines = ["factory orders:"]
        lines += [
            f"  {o.id} {o.part_type} x{o.qty} {o.state} cell={o.cell} done={o.done}"
            f" held={o.held} sends={o.sends} refused={list(o.refused)} {o.note}"
            for o in self.store.orders()
        ]
        lines.append("factory cells:")
        lines += [
            f"  {c.name} {c.status} epoch={c.epoch} seq={c.seq}"
            f" orders_open={c.state.get('orders_open')}"
            for c in self.store.cells().values()
        ]
        lines.append("factory events (last 30):")
        lines += [f"  {e.cell or '-'} {e.text}" for e in self.store.events(limit=30)]
        for name in self.names:
            journal, mailbox = self.journals[name], self.mailboxes[name]
            lines.append(f"{name}: last report {mailbox.reports()[-1:]}")
            lines += [f"  order {o.id} {o.state} {o.note}" for o in mailbox.orders()]
            lines += [
                f"  part {p.id} {p.order_id} {p.location} r{p.route_index} {p.status} {p.note}"
                for p in journal.parts()
                if p.status != "done"
            ]
            lines += [
                f"  open step {s.id} {s.part_id} {s.kind} {s.machine} {s.program}"
                for s in journal.open_steps()
            ]
            lines += [
                f"  alarm {a.id} {a.machine} {a.code} {a.text}" for a in journal.active_alarms()
            ]
            lines += self._physical(name)
        for log in sorted(self.logs.glob("*.log")):
            tail = log.read_text(errors="replace").splitlines()[-40:]
            lines += [f"---- {log.name} (last 40 lines)", *tail]
        broker_log = self.emulated.broker.log_path
        if broker_log.exists():
            lines += ["---- broker (last 15 lines)"]
            lines += broker_log.read_text(errors="replace").splitlines()[-15:]
        return "\n".join(lines)

    # -- the checks ----------------------------------------------------------------------------

    def check_made_once(self) -> None:
        """Every order done, by one cell, with its parts cut once on each mill of its route."""
        state = self.describe()
        orders = {o.id: o for o in self.store.orders()}
        assert set(orders) == {oid for oid, _, _ in BATCH}, state
        for oid, part_type, qty in BATCH:
            o = orders[oid]
            assert (o.part_type, o.qty, o.state, o.done) == (part_type, qty, DONE, qty), state
            # The cells' own records: taken by exactly one cell, the one the factory says.
            holders = [
                name
                for name, mailbox in self.mailboxes.items()
                if any(c.id == oid and c.state != CANCELLED for c in mailbox.orders())
            ]
            assert holders == [o.cell], f"order {oid} at {holders}, factory says {o.cell}\n{state}"
            at = self.mailboxes[o.cell].get_order(oid)
            assert (at.state, at.qty, at.part_type) == (DONE, qty, part_type), state
            parts = self.journals[o.cell].parts(order_id=oid)
            assert [p.status for p in parts] == ["done"] * qty, state
        # No cell has an order the factory did not give it.
        for mailbox in self.mailboxes.values():
            assert {c.id for c in mailbox.orders()} <= set(orders), state
        # The accept deadline's alarm bell: an order accepted by a second cell.
        assert not [e.text for e in self.store.events(limit=10_000) if " too, after " in e.text]
        # The mills' own logs: each part cut once on each mill of its route, as many parts
        # as ordered from each cell, and every one of them out on the conveyor.
        for name in self.names:
            cell = self.cell(name)
            routes = load_cell(self.cell_dir(name)).parts
            mills = {t: sorted(step.mill for step in routes[t].route) for t in PART_TYPES}
            assert mills[PART_TYPES[0]] == mills[PART_TYPES[1]], "the check below needs one route"
            runs = cell.runs_per_part()
            ordered = sum(o.qty for o in orders.values() if o.cell == name)
            assert len(runs) == ordered, (
                f"{name}: {len(runs)} parts cut, {ordered} ordered\n{state}"
            )
            once = dict.fromkeys(mills[PART_TYPES[0]], 1)
            assert {p: r for p, r in runs.items() if r != once} == {}, f"{name}\n{state}"
            assert sorted(cell.outfeed) == sorted(runs), f"{name}\n{state}"
        total = sum(len(self.cell(n).runs_per_part()) for n in self.names)
        assert total == sum(qty for _, _, qty in BATCH), state
        # The factory spread the batch over every cell.
        assert {o.cell for o in orders.values()} == set(self.names), state


def _shown(emulator: object) -> str:
    """What an emulator of any kind shows of itself (the attributes its kind has)."""
    names = ("display", "executing", "activity", "mode", "state")
    return " ".join(f"{n}={getattr(emulator, n)}" for n in names if hasattr(emulator, n))
