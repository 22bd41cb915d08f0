"""``cellctl demo --factory N``: a mixed batch spread over N emulated cells by the factory.

::

    cellctl demo --factory 3                 # 9 parts over 3 cells, figures at the end
    cellctl demo --factory 2 --parts 4 --time-scale 1000 --out /tmp/demo
    cellctl demo --factory 2 --template examples/cell-tending   # cell1 that cell, cell2 a lab cell

Everything is started for you, in ``OUT/factory`` (``--out``, default ``demo-out``):

- a private Mosquitto and N emulated cells (robot, two mills and a PLC each: the example cell,
  or with ``--template DIR`` that cell directory's machines), in this process
  (:class:`cellctl.factory.emulated.EmulatedFactory`);
- each cell's controller in its own process, ``cellctl --cell OUT/factory/cellN run --no-live``,
  its events in ``OUT/factory/cellN/run.log``: a cell is its own program on the shop floor,
  and a controller takes its process's signals, so one process holds one;
- the factory's controller in this process, printing its events a line at a time.

Once every cell is online (the factory dispatches only to a cell that said so, and would give
the whole batch to the first one otherwise) the orders are submitted at once, alternating the
part types the cells make in orders of 1 or 2 parts. When every order has ended, the cells'
controllers get SIGTERM (each finishes the step it is in) and the figures are printed: per cell
the parts made, makespan, the busiest machine's utilization and the parts cut twice according
to the emulated mills' own logs (must be 0); in total the orders, parts, the makespan from the
submit to the last step's end, and the bound of the best split of the batch over the cells
(:mod:`cellctl.factory.bound`, from the durations each cell measured).

Ctrl-C stops it the same way (the cells' controllers are in their own session, so the terminal
signals only this process, which stops them in order); a second Ctrl-C kills them at once.
Exit status: 0 when every part was made once, 1 otherwise, 130 after Ctrl-C.
"""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import signal
import sys
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cellctl.cell.config import PartType, load_cell
from cellctl.cell.estimate import Durations, measured_durations
from cellctl.cell.journal import open_journal
from cellctl.cell.report import Summary, summarize, write_gantt
from cellctl.clock import current_clock
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.errors import UsageError
from cellctl.factory.bound import cell_bound, split_bound
from cellctl.factory.config import load_factory
from cellctl.factory.controller import FactoryController
from cellctl.factory.emulated import EmulatedFactory, check_factory_dir
from cellctl.factory.store import DONE, OPEN_STATES, FactoryOrder, FactoryStore
from cellctl.ui.common import console, stop_signals

#: Parts per cell when ``--parts`` is not given.
PARTS_PER_CELL = 3
#: How long the cells' controllers have to come online (connect to their machines).
ONLINE_TIMEOUT_S = 60.0
#: How long a cell's controller has to finish its step and exit after SIGTERM.
STOP_TIMEOUT_S = 30.0


def mixed_batch(count: int, types: Sequence[str]) -> list[tuple[str, int]]:
    """``count`` parts as orders of 1 or 2, the types taking turns and sharing the count."""
    share = [count // len(types) + (i < count % len(types)) for i in range(len(types))]
    lots: list[list[int]] = []
    for n in share:
        sizes: list[int] = []
        while n > 0:
            sizes.append(min(n, 1 + len(sizes) % 2))
            n -= sizes[-1]
        lots.append(sizes)
    orders = []
    for i in range(max(len(s) for s in lots)):
        orders += [(t, s[i]) for t, s in zip(types, lots, strict=True) if i < len(s)]
    return orders


@dataclass
class CellFigures:
    """One cell's share of the run."""

    name: str
    orders: int
    summary: Summary
    cut_twice: int
    durations: Durations
    last_end: float
    types: Mapping[str, PartType]  # what the cell makes

    @property
    def made(self) -> int:
        return sum(self.summary.parts_made.values())

    def line(self) -> str:
        s = self.summary
        made = ", ".join(f"{n} x {t}" for t, n in sorted(s.parts_made.items())) or "none"
        busiest = max(s.busy_s, key=s.busy_s.__getitem__) if s.busy_s else ""
        orders = f"{self.orders} order" + ("" if self.orders == 1 else "s")
        return (
            f"{self.name}: {orders}, parts made {self.made} ({made}); makespan "
            f"{s.makespan_s:.2f} s; busiest {busiest} {s.utilization(busiest):.1%}; "
            f"parts cut twice {self.cut_twice}"
        )


def _say(text: str) -> None:
    stamp = time.strftime("%H:%M:%S", time.localtime(current_clock().now()))
    console.print(f"{stamp} {text}", markup=False, soft_wrap=True)
    console.file.flush()


async def run_factory_demo(
    cells: int,
    count: int | None,
    time_scale: float,
    out: Path,
    templates: Sequence[Path] = (),
) -> int:
    """Run the demo of the module docstring; return its exit status. ``templates``: the
    cell directories cell1, cell2, ... emulate (the rest: the example cell)."""
    if cells < 2:
        raise UsageError(f"--factory takes 2 cells or more, not {cells}")
    if len(templates) > cells:
        raise UsageError(f"{len(templates)} --template for {cells} cells")
    count = cells * PARTS_PER_CELL if count is None else count
    if count < 1:
        raise UsageError(f"--parts must be at least 1, not {count}")
    # Every type some cell makes, each once, in the cells' order.
    chosen = [*templates, *[EXAMPLE_CELL] * (cells - len(templates))]
    types = list(dict.fromkeys(t for d in chosen for t in load_cell(d).parts))
    batch = mixed_batch(count, types)
    directory = out / "factory"
    check_factory_dir(directory)  # a real factory there is refused before anything is removed
    shutil.rmtree(directory, ignore_errors=True)
    console.print(
        f"[bold]cellctl demo --factory {cells}[/bold]: a private Mosquitto, {cells} emulated "
        f"cells (time scale {time_scale:g}) each run by its own `cellctl run`, and the "
        f"factory; batch: {count} parts in {len(batch)} orders ("
        + ", ".join(f"{n} x {t}" for t, n in _per_type(batch).items())
        + ")",
        soft_wrap=True,
    )
    stop, hurry = asyncio.Event(), asyncio.Event()

    def on_signal() -> None:
        if stop.is_set():
            hurry.set()
            return
        _say("stopping: the cells finish their steps (Ctrl-C again to kill them)")
        stop.set()

    plant = EmulatedFactory(directory, cells=cells, time_scale=time_scale, templates=templates)
    controllers = CellControllers(plant.cell_dirs)
    # Ctrl-C, SIGTERM: ours from here, as found again once the finally below begins.
    signals = contextlib.ExitStack()
    signals.enter_context(stop_signals(on_signal))
    try:
        await plant.start()
        console.print(
            f"Mosquitto on {plant.broker.url}; files in {directory}", markup=False, soft_wrap=True
        )
        await controllers.start()
        for cell_dir in plant.cell_dirs:
            console.print(
                f"  cellctl --cell {cell_dir} run --no-live  (log: {cell_dir / 'run.log'})",
                markup=False,
                soft_wrap=True,
            )
        config = load_factory(directory)
        with FactoryStore(config.state_path) as store:
            factory = FactoryController(config, store, log=_say)
            factory_stop = asyncio.Event()
            task = asyncio.create_task(factory.run(factory_stop))
            try:
                started = await _batch(store, factory, plant.names, controllers, batch, stop)
                await controllers.stop(hurry)  # the factory hears them go offline
            finally:
                factory_stop.set()
                await task
            orders = store.orders()
    finally:
        await controllers.stop(hurry)
        await plant.close()
        signals.close()
    if stop.is_set():
        console.print("interrupted")
        return 130
    figures = [
        _cell_figures(name, cell_dir, started, plant.cells[i].runs_per_part(), orders)
        for i, (name, cell_dir) in enumerate(zip(plant.names, plant.cell_dirs, strict=True))
    ]
    return _report(figures, orders, batch, started, out)


def _per_type(batch: Sequence[tuple[str, int]]) -> dict[str, int]:
    counts: Counter[str] = Counter()
    for t, n in batch:
        counts[t] += n
    return dict(counts)


class CellControllers:
    """``cellctl --cell DIR run --no-live`` for each cell directory, each in its own session
    (so a terminal's Ctrl-C reaches only us), its output in ``DIR/run.log``::

        controllers = CellControllers(plant.cell_dirs)
        await controllers.start()
        controllers.check()            # UsageError when one has exited, with its last lines
        await controllers.stop()       # SIGTERM, wait; kill after STOP_TIMEOUT_S or on hurry
    """

    def __init__(self, cell_dirs: Sequence[Path]) -> None:
        self.cell_dirs = list(cell_dirs)
        self.procs: list[asyncio.subprocess.Process] = []

    async def start(self) -> None:
        for cell_dir in self.cell_dirs:
            with (cell_dir / "run.log").open("wb") as log:
                proc = await asyncio.create_subprocess_exec(
                    sys.executable,
                    "-m",
                    "cellctl",
                    "--cell",
                    str(cell_dir),
                    "run",
                    "--no-live",
                    stdin=asyncio.subprocess.DEVNULL,
                    stdout=log,
                    stderr=asyncio.subprocess.STDOUT,
                    start_new_session=True,
                )
            self.procs.append(proc)

    def check(self) -> None:
        """Raise UsageError if a controller has exited (it should run until stopped)."""
        for cell_dir, proc in zip(self.cell_dirs, self.procs, strict=False):
            if proc.returncode is not None:
                log = cell_dir / "run.log"
                tail = log.read_text(errors="replace").strip().splitlines()[-3:]
                raise UsageError(
                    f"the controller of {cell_dir} exited ({proc.returncode}): " + " | ".join(tail)
                )

    async def stop(self, hurry: asyncio.Event | None = None) -> None:
        """SIGTERM each controller (it finishes its steps) and wait; kill what is left after
        :data:`STOP_TIMEOUT_S`, or at once when ``hurry`` is set."""
        running = [p for p in self.procs if p.returncode is None]
        if not running:
            return
        for p in running:
            with contextlib.suppress(ProcessLookupError):
                p.send_signal(signal.SIGTERM)
        exited: asyncio.Future[Any] = asyncio.gather(*(p.wait() for p in running))
        hurried: asyncio.Future[Any] = asyncio.ensure_future((hurry or asyncio.Event()).wait())
        try:
            await asyncio.wait(
                {exited, hurried}, timeout=STOP_TIMEOUT_S, return_when=asyncio.FIRST_COMPLETED
            )
        finally:
            hurried.cancel()
            for p in running:
                if p.returncode is None:
                    with contextlib.suppress(ProcessLookupError):
                        p.kill()
            await exited


async def wait_online(
    store: FactoryStore,
    names: Sequence[str],
    controllers: CellControllers,
    stop: asyncio.Event,
    timeout: float = ONLINE_TIMEOUT_S,
) -> None:
    """Until the factory has heard every cell of ``names`` say it is online, with the part
    types it makes (or ``stop``); UsageError after ``timeout`` s."""
    clock = current_clock()
    deadline = clock.monotonic() + timeout
    while not stop.is_set():
        controllers.check()
        seen = store.cells()
        if all(n in seen and seen[n].status == "online" and seen[n].part_types for n in names):
            return
        if clock.monotonic() > deadline:
            raise UsageError(
                f"the cells did not come online within {timeout:g} s (see each cell's run.log)"
            )
        await clock.sleep(0.05)


async def _batch(
    store: FactoryStore,
    factory: FactoryController,
    names: Sequence[str],
    controllers: CellControllers,
    batch: Sequence[tuple[str, int]],
    stop: asyncio.Event,
) -> float:
    """Submit ``batch`` once every cell is online; return when every order has ended (or
    ``stop``). Returns the time of the submit."""
    await wait_online(store, names, controllers, stop)
    started = current_clock().now()
    if stop.is_set():
        return started
    for i, (part_type, qty) in enumerate(batch, start=1):
        store.submit(part_type, qty, order_id=f"F{i}")
    factory.poke()
    _say(f"{len(batch)} orders submitted")
    while not stop.is_set() and store.orders(OPEN_STATES):
        controllers.check()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(0.1):
                await stop.wait()
    return started


def _cell_figures(
    name: str,
    cell_dir: Path,
    since: float,
    runs: dict[str, dict[str, int]],
    orders: Sequence[FactoryOrder],
) -> CellFigures:
    config = load_cell(cell_dir)
    machines = [config.robot.name, *(m.name for m in config.mills)]
    with open_journal(cell_dir) as journal:
        summary = summarize(journal, machines, since=since)
        steps = [s for s in journal.steps() if s.started >= since]
        write_gantt(
            journal,
            machines,
            cell_dir / "gantt.svg",
            since=since,
            title=f"{name}: makespan {summary.makespan_s:.1f} s",
        )
    twice = sum(1 for r in runs.values() if any(n > 1 for n in r.values()))
    ends = [s.ended for s in steps if s.ended is not None]
    return CellFigures(
        name,
        sum(1 for o in orders if o.cell == name),
        summary,
        twice,
        measured_durations(steps),
        max(ends, default=since),
        config.parts,
    )


def _report(
    figures: Sequence[CellFigures],
    orders: Sequence[FactoryOrder],
    batch: Sequence[tuple[str, int]],
    started: float,
    out: Path,
) -> int:
    console.print()
    for f in figures:
        console.print(f.line(), markup=False, soft_wrap=True)
    wanted = sum(n for _, n in batch)
    made = sum(f.made for f in figures)
    twice = sum(f.cut_twice for f in figures)
    done = sum(1 for o in orders if o.state == DONE)
    makespan = max(f.last_end for f in figures) - started
    pooled = Durations()
    for f in figures:
        pooled = pooled.filled(f.durations)
    try:
        bounds = {f.name: cell_bound(f.types, f.durations.filled(pooled)) for f in figures}
        bound, _ = split_bound(bounds, _per_type(batch))
        versus = f"; bound of the best split {bound:.2f} s (makespan/bound {makespan / bound:.3f})"
    except (KeyError, ZeroDivisionError):
        versus = ""  # a step no cell finished: no measured duration to bound it with
    console.print(
        f"total: {len(orders)} orders ({done} done), parts made {made} of {wanted}; makespan "
        f"{makespan:.2f} s from the submit{versus}; parts cut twice {twice}",
        markup=False,
        soft_wrap=True,
    )
    console.print(
        f"Gantt charts: {out / 'factory' / 'cellN' / 'gantt.svg'}", markup=False, soft_wrap=True
    )
    return 0 if made == wanted and done == len(orders) and twice == 0 else 1
