"""A cell as the control API sees it: attached to the running controller, or standalone.

:class:`AttachedCell` wraps a running :class:`~cellctl.cell.controller.CellController`: manual
functions go through its command interface (only on a machine out of automatic service).
:class:`LocalCell` is the cell without a controller: it opens each machine's link itself on
first use (holding its locks) and keeps it until closed, as the source's tool-kit did::

    async with LocalCell(Path("cell"), refs) as cell:
        async with cell.driver("robot") as robot:
            await robot.status()
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import tomllib
from abc import ABC, abstractmethod
from collections.abc import AsyncIterator, Iterator, Mapping
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self, cast

from cellctl.cell.journal import JOURNAL_FILE, Journal, open_journal
from cellctl.cell.machines import open_machine
from cellctl.cell.model import MachineView
from cellctl.clock import current_clock
from cellctl.drivers.plc import ModbusPlc
from cellctl.drivers.state import StateStore
from cellctl.errors import CellctlError, UsageError, unknown_machine
from cellctl.kinds import Condition, registry
from cellctl.link import TrafficLog
from cellctl.mailbox import MAILBOX_FILE, Mailbox, open_mailbox
from cellctl.protocol.plc import PlcMap, canonical
from cellctl.service.machines import MachineRef, load_cell_file
from cellctl.service.operator import CellPlaces
from cellctl.service.orderdue import list_orders  # each order with its due time, late
from cellctl.service.status import (
    STATUS_EVENTS,
    CellInfo,
    CellMode,
    CellStatus,
    build_status,
)

if TYPE_CHECKING:
    from cellctl.cell.controller import CellController

#: Events a status carries.
SNAPSHOT_EVENTS = STATUS_EVENTS
#: Chunks of traffic a standalone cell keeps per process.
TRAFFIC_KEPT = 4000


class CellAccess(ABC):
    """What the API's methods need of a cell (see the module docstring)."""

    mode: str
    directory: Path

    @abstractmethod
    def journal(self) -> Journal | None:
        """The cell's journal (None if the cell never ran)."""

    @abstractmethod
    def mailbox(self) -> Mailbox:
        """The cell's mailbox."""

    @contextlib.contextmanager
    def work_to_plan(self) -> Iterator[tuple[Mailbox, Journal | None]]:
        """The mailbox and journal a plan reads the cell's work from, while the context
        lasts: the cell's own (a running controller's)."""
        yield self.mailbox(), self.journal()

    @abstractmethod
    def machines(self) -> dict[str, str]:
        """Machine name -> family (``robot`` or ``mill``)."""

    @abstractmethod
    def machine_kinds(self) -> dict[str, str]:
        """Machine name -> kind (cell.toml's ``kind``): whose manual functions it has."""

    @abstractmethod
    def driver(
        self, name: str, *, observe: bool = False
    ) -> contextlib.AbstractAsyncContextManager[Any]:
        """The driver of ``name`` for a manual function (refused if not allowed now);
        ``observe``: the function only reads the machine (allowed in automatic service)."""

    @abstractmethod
    def status(self) -> CellStatus:
        """The cell's status (:mod:`cellctl.service.status`): built anew at each call."""

    def snapshot(self) -> dict[str, Any]:
        """The cell's status as JSON (what ``cell.status`` answers)."""
        return self.status().model_dump(mode="json")

    @abstractmethod
    def traffic(self, name: str, limit: int) -> list[dict[str, Any]]:
        """The last bytes of machine ``name``'s link, both ways."""

    def methods(self) -> Mapping[str, Any]:
        """API methods of its own this access serves beside the common table (each a
        :class:`~cellctl.service.methods.Method`, by name): none for a cell."""
        return {}

    def layout(self) -> dict[str, Any] | None:
        """Its layout (``cell.layout``'s answer) when it has one of its own, not read from
        a cell.toml (a DNC shop's machines); None: the cell's."""
        return None

    def known_machines(self) -> list[str] | None:
        """The machine names the cell knows (None: it cannot say)."""
        return list(self.machines())

    def places(self) -> CellPlaces | None:
        """Where a part can be in the cell: what a released part's place is checked against
        (None: the cell cannot say)."""
        return CellPlaces.of_file(load_cell_file(self.directory))

    def require_machine(self, name: str) -> None:
        """Refuse machine ``name`` if the cell does not know it, whether or not a controller
        runs: the name is the first thing wrong."""
        known = self.known_machines()
        if known is not None and name not in known:
            raise unknown_machine(name, known)

    def controller(self) -> CellController:
        """The running controller: UsageError when none runs."""
        raise UsageError(f"no controller runs on {self.directory}: start `cellctl run` for that")

    def poke(self) -> None:  # noqa: B027 - nothing to wake without a controller
        """Something the operator did changed the journal or mailbox (wake the controller)."""

    async def close(self) -> None:  # noqa: B027 - an attached cell holds nothing of its own
        """Release what the access holds (links, files)."""

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()


def traffic_rows(log: TrafficLog, label: str, limit: int) -> list[dict[str, Any]]:
    """A traffic tail as JSON rows: time, direction (``>>`` sent, ``<<`` received), hex, text."""
    return [
        {
            "time": t,
            "dir": d,
            "hex": data.hex(" ").upper(),
            "text": "".join(chr(b) if 32 <= b < 127 else "." for b in data),
        }
        for t, d, data in log.tail(label, limit)
    ]


class AttachedCell(CellAccess):
    """The cell of a controller running in this process."""

    mode = "attached"

    def __init__(self, controller: CellController) -> None:
        self._controller = controller
        self.directory = controller.config.directory

    def controller(self) -> CellController:
        return self._controller

    def journal(self) -> Journal:
        return self._controller.journal

    def mailbox(self) -> Mailbox:
        return cast(Mailbox, self._controller.mailbox)

    def machines(self) -> dict[str, str]:
        c = self._controller.config
        return {c.robot.name: "robot", **{m.name: "mill" for m in c.mills}}

    def machine_kinds(self) -> dict[str, str]:
        c = self._controller.config
        return {c.robot.name: c.robot.kind, **{m.name: m.kind for m in c.mills}}

    def driver(
        self, name: str, *, observe: bool = False
    ) -> contextlib.AbstractAsyncContextManager[Any]:
        if observe:
            return self._controller.observe(name)
        return self._controller.manual(name)

    def poke(self) -> None:
        self._controller.poke()

    def places(self) -> CellPlaces:
        return CellPlaces.of_config(self._controller.config)

    def status(self) -> CellStatus:
        c = self._controller
        journal = c.journal
        cell = CellInfo(
            name=c.config.name,
            directory=str(self.directory),
            access="attached",
            mode=_mode(c),
            paused=c.paused,
            started_at=c.started_at,
            pid=os.getpid(),
            time=current_clock().now(),
        )
        estimates = {
            (step.mill, step.name): step.machining_s
            for part in c.config.parts.values()
            for step in part.route
            if step.machining_s > 0
        }
        return build_status(
            cell=cell,
            views=c.machines,
            families={**self.machines(), "plc": "plc"},
            out_of_service=journal.machines_out_of_service(),
            manual=c.manual_use,
            manual_steps=c.manual_steps,
            journal=journal,
            orders=list_orders(self.mailbox(), journal, config=c.config),
            events=[(e.time, e.text) for e in c.events[-SNAPSHOT_EVENTS:]],
            estimates=estimates,
        )

    def traffic(self, name: str, limit: int) -> list[dict[str, Any]]:
        if name not in self.machines():
            raise unknown_machine(name, self.machines())
        return traffic_rows(self._controller.traffic, name, limit)


class LocalCell(CellAccess):
    """A cell (or one ad-hoc machine) driven from this process, no controller running.

    ``refs`` are the machines it may open; ``trace`` logs every byte to a file too.
    """

    mode = "standalone"

    def __init__(
        self,
        directory: Path,
        refs: dict[str, MachineRef],
        *,
        trace: str | Path | None = None,
        readiness: str | None = None,
    ) -> None:
        self.directory = directory
        self.refs = refs
        self._trace_file = TrafficLog(trace) if trace else None
        self.traffic_log = TrafficLog(None, keep=TRAFFIC_KEPT)
        self._readiness = readiness
        self._drivers: dict[str, Any] = {}
        self._locks: dict[str, asyncio.Lock] = {}
        self._journal: Journal | None = None
        self._mailbox: Mailbox | None = None
        self.states: dict[str, str] = {}
        self.steps: dict[str, str] = {}
        self.conditions: dict[str, Condition] = {}
        self.events: list[dict[str, Any]] = []
        self.started_at = current_clock().now()

    def journal(self) -> Journal | None:
        if self._journal is None and (self.directory / JOURNAL_FILE).exists():
            self._journal = open_journal(self.directory)
        return self._journal

    def mailbox(self) -> Mailbox:
        if self._mailbox is None:
            self._mailbox = open_mailbox(self.directory)
        return self._mailbox

    @contextlib.contextmanager
    def work_to_plan(self) -> Iterator[tuple[Mailbox, Journal | None]]:
        """Copies of the cell's mailbox and journal, read without a write
        (:func:`~cellctl.plan.snapshot.copied_stores`): a plan of a cell no controller runs
        writes nothing into it, not even a mailbox where there is none."""
        from cellctl.plan.snapshot import copied_stores

        with copied_stores(self.directory) as stores:
            yield stores

    def machines(self) -> dict[str, str]:
        return {name: registry.family_of(ref.kind) for name, ref in self.refs.items()}

    def machine_kinds(self) -> dict[str, str]:
        return {name: ref.kind for name, ref in self.refs.items()}

    def known_machines(self) -> list[str] | None:
        """The machines it may open, else the cell.toml's (None: no cell.toml to read)."""
        if self.refs:
            return list(self.refs)
        try:
            with (self.directory / "cell.toml").open("rb") as f:
                machines = tomllib.load(f).get("machines")
        except (OSError, tomllib.TOMLDecodeError):
            return None
        return list(machines) if isinstance(machines, dict) else None

    def note(self, text: str) -> None:
        """An event for the snapshot (what a function did)."""
        self.events.append({"time": current_clock().now(), "text": text})
        del self.events[:-SNAPSHOT_EVENTS]

    @contextlib.asynccontextmanager
    async def driver(self, name: str, *, observe: bool = False) -> AsyncIterator[Any]:
        if name not in self.refs:
            raise unknown_machine(name, self.refs)
        lock = self._locks.setdefault(name, asyncio.Lock())
        async with lock:
            driver = self._drivers.get(name)
            if driver is not None and driver.link.closed:
                with contextlib.suppress(CellctlError, OSError):
                    await driver.close()
                driver = None
            if driver is None:
                driver = await self._open(self.refs[name])
                self._drivers[name] = driver
            self.steps[name] = "manual"
            try:
                yield driver
            finally:
                self.steps[name] = ""
                self.states[name] = _state_of(driver)
                self.conditions[name] = _condition_of(driver)

    async def _open(self, ref: MachineRef) -> Any:
        options = dict(ref.options)
        # ``go_output`` here is the command line's --start-signal, not a kind's option.
        signal = options.pop("go_output", None)
        kind = registry.kind(ref.kind)
        if self._readiness and "readiness" in kind.options.model_fields:
            options["readiness"] = self._readiness
        start = self._start_output(ref, signal) if kind.family == "mill" else None
        return await open_machine(
            ref.kind,
            ref.name,
            ref.url,
            ref.settings,
            options,
            store=StateStore(self.directory),
            trace=_Tee(self.traffic_log, self._trace_file),
            start_output=start,
        )

    def _start_output(self, ref: MachineRef, signal: str | None) -> _PlcPulse | None:
        """GO pulses the PLC coil wired to the mill's start input (a connection per pulse):
        ``signal``, else the machine's ``go_output``, else ``go_N`` for the cell's N-th mill."""
        cell = load_cell_file(self.directory)
        raw = cell.get("plc")
        table = raw if isinstance(raw, dict) else {}
        machines = cell.get("machines")
        entry = machines.get(ref.name) if isinstance(machines, dict) else None
        if signal is None and isinstance(entry, dict) and isinstance(entry.get("go_output"), str):
            signal = entry["go_output"]
        if signal is None and raw is not None:
            mills = [n for n, r in self.refs.items() if registry.family_of(r.kind) == "mill"]
            signal = f"go_{mills.index(ref.name) + 1}"
        if signal is None:
            return None
        return _PlcPulse(PlcMap.from_toml(table), canonical(signal))

    def status(self) -> CellStatus:
        views = {
            name: MachineView(
                name,
                ref.kind,
                state=self.states.get(
                    name, "connected" if name in self._drivers else "not connected"
                ),
                step=self.steps.get(name, ""),
                in_service=False,
                machine_condition=self.conditions.get(
                    name, Condition.NOT_READY if name in self._drivers else Condition.OFFLINE
                ),
            )
            for name, ref in self.refs.items()
        }
        raw = load_cell_file(self.directory).get("cell")
        named = raw.get("name") if isinstance(raw, dict) else None
        cell = CellInfo(
            name=str(named or self.directory.resolve().name),
            directory=str(self.directory),
            access="standalone",
            mode=CellMode.NO_CONTROLLER,
            paused=False,
            started_at=self.started_at,
            pid=os.getpid(),
            time=current_clock().now(),
        )
        mailbox = self.mailbox() if (self.directory / MAILBOX_FILE).exists() else None
        journal = self.journal()
        return build_status(
            cell=cell,
            views=views,
            families=self.machines(),
            out_of_service=dict.fromkeys(self.refs, "standalone: no controller runs"),
            manual=self.refs,
            journal=journal,
            orders=list_orders(mailbox, journal) if mailbox is not None else [],
            events=[(e["time"], e["text"]) for e in self.events],
        )

    async def refresh(self) -> None:
        """Look again at each machine that waits for its operator (a mill whose setup went
        out waits for NEXT), when its link is free: its state moves on without a call."""
        for name, driver in list(self._drivers.items()):
            host = getattr(driver, "host_status", None)
            lock = self._locks.get(name)
            if host is None or lock is None or lock.locked():
                continue
            if not getattr(host(), "awaiting_operator", False):
                continue
            async with lock:
                with contextlib.suppress(CellctlError, OSError):
                    await driver.status()
                self.states[name] = _state_of(driver)
                self.conditions[name] = _condition_of(driver)

    def traffic(self, name: str, limit: int) -> list[dict[str, Any]]:
        if name not in self.refs:
            raise UsageError(
                f"no controller runs on {self.directory}: the traffic of {name!r} is the "
                "running controller's (`cellctl run`); a command of its own shows its bytes "
                "with --trace FILE"
            )
        return traffic_rows(self.traffic_log, name, limit)

    async def close(self) -> None:
        for driver in self._drivers.values():
            with contextlib.suppress(CellctlError, OSError):
                await driver.close()
        self._drivers.clear()
        for store in (self._journal, self._mailbox):
            if store is not None:
                store.close()
        self._journal = self._mailbox = None
        if self._trace_file is not None:
            self._trace_file.close()


class _PlcPulse:
    """A start output on a PLC coil: one Modbus connection per pulse, as long as the driver
    asks."""

    def __init__(self, plc_map: PlcMap, coil: str) -> None:
        self.plc_map = plc_map
        self.coil = coil

    async def pulse(self, seconds: float) -> None:
        async with await ModbusPlc.connect(self.plc_map.url, self.plc_map) as plc:
            await plc.pulse(self.coil, seconds)


class _Tee(TrafficLog):
    """The in-memory tail, and the user's trace file when one was asked for."""

    def __init__(self, memory: TrafficLog, file: TrafficLog | None) -> None:
        super().__init__(None, keep=1)
        self._memory = memory
        self._file = file

    def record(self, label: str, direction: str, data: bytes, when: float) -> None:
        self._memory.record(label, direction, data, when)
        if self._file is not None:
            self._file.record(label, direction, data, when)


def _state_of(driver: Any) -> str:
    """The driver's last known state in the machine's words."""
    return _host(driver)[0]


def _condition_of(driver: Any) -> Condition:
    """The condition a driver's last known state shows (a closed link: offline)."""
    return _host(driver)[1]


def _host(driver: Any) -> tuple[str, Condition]:
    """What a driver knows of its machine without a byte sent: its words and condition."""
    link = getattr(driver, "link", None)
    if link is not None and link.closed:
        return "link closed", Condition.OFFLINE
    status = getattr(driver, "host_status", None)
    if status is None:
        return "connected", Condition.NOT_READY
    shown = status()
    words = (
        getattr(shown, "host_text", None)
        or getattr(shown, "text", None)
        or getattr(shown, "state_text", "connected")
    )
    said = getattr(shown, "condition", None)
    if isinstance(said, Condition):
        return str(words), said
    kind_condition = getattr(shown, "kind_condition", None)
    return str(words), kind_condition if isinstance(
        kind_condition, Condition
    ) else Condition.NOT_READY


def _mode(controller: CellController) -> CellMode:
    """What the controller is doing: an active emergency stop (the PLC's input, or the
    operator's alarm) first, then stopping, paused, running."""
    estop = not controller.inputs.get("estop_ok", True) or (
        controller.journal.open_alarm("cell", "estop") is not None
    )
    if estop:
        return CellMode.EMERGENCY_STOP
    if controller.stopping:
        return CellMode.STOPPING
    return CellMode.PAUSED if controller.paused else CellMode.RUNNING
