"""The whole cell, emulated: robot, two mills and the PLC, wired as the example cell is.

Each machine's emulator comes from its kind (the registry): the robot family's emulator
takes ``set_input`` and ``output_hooks`` (and ``set_output`` to start with a part in a vise),
a mill's takes ``cycle_start``, ``run_hooks`` and ``start`` (docs/kinds.md). A template
with other kinds is served the same way.

::

    cell = EmulatedCell(time_scale=100.0)
    await cell.start(Path("cell"))          # copies the example cell there, writes its cell.toml
    ...                                     # a controller runs the cell from Path("cell")
    cell.switch_on_at_cut("cnc1", "stall")  # cnc1's next cut stalls (not a setup block)
    cell.runs_per_part()                    # {"P1": {"cnc1": 1, "cnc2": 1}, ...}
    await cell.close()

The cell directory is the emulation's: a cell.toml there that it did not write (no
:data:`EMULATED_HEADER` first line: a real cell's) is refused before a file is touched;
one it wrote before is written anew, as the programs beside it are copied anew.

``EmulatedCell(time_scale=1.0, links="mem")`` serves every machine on ``mem://`` in the
running event loop instead (``mem://robot``, ``mem://cnc1``, the PLC's Modbus/TCP on
``mem://plc``; ``mem_prefix`` in front of each name), what a run on virtual time takes
(:func:`cellctl.clock.run_virtual`: the machines' own times and lines, scale 1). A robot
whose kind serves interfaces of its own over TCP (the UR's three) cannot join such a cell.

Serving: the robot on a pty (``robot.pty`` in the cell directory, a symlink that follows a
new pty after a dropped connection; or any ``robot_listen``), the mills over RFC 2217 (their
readiness is the CTS modem line), the PLC over Modbus/TCP, all on this machine. Every
machine time is divided by ``time_scale`` and so is every character's time on the line
(the baud rate written to ``cell.toml`` is multiplied by it), so transfer and machining keep
their real proportions.

Wiring (the PLC's own logic, as the example cell's programs expect it; **assumed**):

- PLC inputs drive robot inputs 1-8: pallet at the pick-up, CNC 1 door open, CNC 1 vise open,
  CNC 1 vise closed, CNC 2 door open, CNC 2 vise open, CNC 2 vise closed, outfeed clear.
- Robot outputs 1 and 2 drive the vise coils of CNC 1 and CNC 2; output 7 (blank taken)
  lifts the blank off its pallet; output 5 (part placed) fills the outfeed, which clears
  after the PLC's outfeed time.
- The PLC's GO coils start the loaded program of each mill.

The cell also tracks each physical part — the blank a pallet brings, the gripper, each vise,
the outfeed — so the mills' execution log says which part each program cut
(:attr:`EmulatedCell.cuts`): the record a test checks "no program ran twice for one part"
against, independent of the controller's journal.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import shutil
import tomllib
from collections import defaultdict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from cellctl.clock import Clock, current_clock, emulator_clock
from cellctl.emulators.celltoml import CELL_DEADLINES, DEADLINE_NOTE, is_options, real_cell_toml
from cellctl.emulators.header import EMULATED_HEADER, written_by_emulation
from cellctl.emulators.line import LineNoise
from cellctl.emulators.memserve import serve_mem
from cellctl.emulators.plc import FAULTS as PLC_FAULTS
from cellctl.emulators.plc import PlcEmulator
from cellctl.emulators.serve import (
    CELL_TIME_SCALE,
    MIN_DEADLINE_S,
    EmulatedDevice,
    SelfServed,
    Server,
    claim_pty_listen,
    pty_link_path,
    scaled_deadline,
    serve,
)
from cellctl.emulators.switches import check_switch
from cellctl.errors import UsageError
from cellctl.kinds import registry
from cellctl.kinds.kind import EmulatorSpec
from cellctl.link import LineSettings
from cellctl.link.lock import OwnerLock
from cellctl.protocol.plc import EXAMPLE_WIRING
from cellctl.tasks import cancel_and_wait

#: The example cell (cell.toml, robot/, programs/): package data, so an installed cellctl has
#: it wherever it runs; examples/cell in the repository links to it. Copied by
#: :meth:`EmulatedCell.start`. cellctl is installed unpacked (a wheel, pipx, a checkout), where
#: the package's files are a directory on disk.
EXAMPLE_CELL = Path(str(resources.files("cellctl").joinpath("examples", "cell")))

BASE_LINE = LineSettings(4800, 7, "E", 2)

__all__ = [
    "CUT_FAULTS",
    "EMULATED_HEADER",
    "MIN_DEADLINE_S",
    "EmulatedCell",
    "check_cell_dir",
    "real_cell_toml",
    "scaled_deadline",
    "written_by_emulation",
]

#: A mill's fault switches that act as the block running ends (the Dyna 2400's ``stall``: its
#: READY never comes after it). Switched on as the cell starts, one takes the mill's setup
#: block, the first it runs; :meth:`EmulatedCell.switch_on_at_cut` waits for a cut instead.
CUT_FAULTS = frozenset({"stall"})


#: The example cell's wiring, one table (:data:`cellctl.protocol.plc.EXAMPLE_WIRING`).
ROBOT_INPUTS = EXAMPLE_WIRING.inputs
ROBOT_INPUTS_INVERTED = EXAMPLE_WIRING.inverted
VISE_OUTPUTS = EXAMPLE_WIRING.vise_outputs  # robot output -> mill whose vise it closes
BLANK_TAKEN_OUTPUT = EXAMPLE_WIRING.blank_taken_output
PART_PLACED_OUTPUT = EXAMPLE_WIRING.part_placed_output


@dataclass(frozen=True)
class Cut:
    """One program a mill ran, and the physical part that was in its vise."""

    mill: str
    part: str | None
    time: float


class EmulatedCell:
    """Robot, two mills and a PLC wired together (see module docstring)."""

    def __init__(
        self,
        *,
        time_scale: float | None = None,
        clock: Clock | None = None,
        pacing: bool = True,
        robot_listen: str = "pty",
        host: str = "127.0.0.1",
        mill_names: tuple[str, ...] = ("cnc1", "cnc2"),
        template: Path | None = None,
        links: Literal["real", "mem"] = "real",
        mem_prefix: str = "",
        seed: int | None = None,
    ) -> None:
        # No clock and no scale: the cell's default scale on the real clock.
        if clock is None and time_scale is None:
            time_scale = CELL_TIME_SCALE
        self._clock = emulator_clock(clock, time_scale)
        time_scale = self.time_scale
        if links not in ("real", "mem"):
            raise UsageError(f"links must be 'real' or 'mem', not {links!r}")
        self.links = links
        self.mem_prefix = mem_prefix
        self.pacing = pacing
        self.robot_listen = robot_listen
        self.host = host
        self.mill_names = mill_names
        self.line = LineSettings(
            int(BASE_LINE.baudrate * time_scale), BASE_LINE.bytesize, BASE_LINE.parity, 2
        )
        self.template = template or EXAMPLE_CELL
        self.kinds = _machine_kinds(self.template)
        self.seed = seed  # of everything random in the machines (None: unseeded, as before)
        spec = self._spec
        robots = [n for n, k in self.kinds.items() if registry.family_of(k) == "robot"]
        if not robots:
            raise UsageError(f"{self.template / 'cell.toml'}: no robot machine to emulate")
        self.robot_name = robots[0]
        self.robot: Any = registry.kind(self.kinds[self.robot_name]).emulator(spec(self.robot_name))
        mills = [n for n, k in self.kinds.items() if registry.family_of(k) == "mill"]
        self.mill_names = tuple(mills) if template is not None else mill_names
        self.mills: dict[str, Any] = {
            name: registry.kind(self.kinds[name]).emulator(spec(name)) for name in self.mill_names
        }
        #: Each machine's line: its kind's default line, its baud rate times ``time_scale``.
        self.lines = {
            name: scaled_line(registry.kind(kind).line_settings, time_scale)
            for name, kind in self.kinds.items()
        }
        self.plc = PlcEmulator(clock=self._clock, on_go=self._go)
        self.servers: dict[str, Server | SelfServed] = {}
        self.plc_url = ""
        # physical parts
        self._next_blank = 0
        self.pallet_part: str | None = None
        self.gripper: str | None = None
        self.vise: dict[int, str | None] = {1: None, 2: None}
        self.outfeed: list[str] = []
        self.cuts: list[Cut] = []
        self._head_start: dict[str, tuple[str, float]] = {}  # mill -> (part, machine s done)
        self._at_cut: dict[str, list[tuple[str, str | None]]] = {}  # mill -> faults to switch on
        self._tasks: set[asyncio.Task[None]] = set()

    def machine_seed(self, name: str) -> int | None:
        """Machine ``name``'s seed: from the cell's ``seed`` and its name (None: unseeded)."""
        return None if self.seed is None else random.Random(f"{self.seed}:{name}").getrandbits(63)

    def _spec(self, name: str) -> EmulatorSpec:
        """Machine ``name``'s emulator spec: its seed for a kind that draws (``extra``)."""
        seed = self.machine_seed(name)
        return EmulatorSpec(clock=self._clock, extra={} if seed is None else {"seed": seed})

    def set_fault(self, machine: str, name: str, arg: str | None = None) -> None:
        """Switch ``machine``'s (``"plc"``: the PLC's) emulator fault ``name`` on; a line
        noise with no SEED of its own draws from the machine's seed (:meth:`machine_seed`)."""
        target = self.machine(machine)
        target.set_fault(name, arg)
        noise = getattr(target, "noise", None)
        if isinstance(noise, LineNoise) and noise.seed is None and self.seed is not None:
            target.noise = LineNoise(noise.rate, self.machine_seed(machine))

    def fault_tables(self) -> dict[str, Mapping[str, str]]:
        """Each machine's fault switches (its kind's table; ``plc``: the PLC's), the robot's
        also as ``robot``: what ``--fault MACHINE:NAME[=ARG]`` and the panel's ``fault`` are
        checked against (:func:`~cellctl.emulators.switches.check_fault`)."""
        robot = registry.kind(self.kinds[self.robot_name]).faults
        tables: dict[str, Mapping[str, str]] = {self.robot_name: robot, "robot": robot}
        tables.update({m: registry.kind(self.kinds[m]).faults for m in self.mill_names})
        tables["plc"] = PLC_FAULTS
        return tables

    def machine(self, name: str) -> Any:
        """The emulator of machine ``name`` (``"plc"``: the PLC)."""
        return {"plc": self.plc, self.robot_name: self.robot, **self.mills}[name]

    @property
    def clock(self) -> Clock:
        """What every machine of the cell runs on: the clock given (``clock=``, or
        ``time_scale=`` as RealClock(time_scale)), else the running loop's."""
        return self._clock or current_clock()

    @property
    def time_scale(self) -> float:
        """Seconds of machine time per second of the cell's clock."""
        return self.clock.time_scale

    # -- wiring -----------------------------------------------------------------------------------

    def _go(self, n: int) -> None:
        self.mills[self.mill_names[n - 1]].cycle_start()

    def _plc_input(self, name: str, value: bool) -> None:
        if name in ROBOT_INPUTS:
            self.robot.set_input(ROBOT_INPUTS[name], value)
        if name in ROBOT_INPUTS_INVERTED:
            self.robot.set_input(ROBOT_INPUTS_INVERTED[name], not value)
        if name == "pallet_present" and value:
            self._next_blank += 1
            self.pallet_part = f"P{self._next_blank}"

    def _robot_output(self, port: int, value: bool) -> None:
        if port in VISE_OUTPUTS:
            n = VISE_OUTPUTS[port]
            self.plc.set_coil(f"clamp_{n}", value)
            if value and self.gripper is not None:
                self.vise[n], self.gripper = self.gripper, None
            elif not value and self.vise[n] is not None:
                self.gripper, self.vise[n] = self.vise[n], None
        elif port == BLANK_TAKEN_OUTPUT and value:
            self.gripper, self.pallet_part = self.pallet_part, None
            self.plc.take_pallet()
        elif port == PART_PLACED_OUTPUT and value:
            if self.gripper is not None:
                self.outfeed.append(self.gripper)
                self.gripper = None
            self.plc.set_input("outfeed_clear", False)
            self._spawn(self._clear_outfeed())

    def place(self, mill: str, part: str, *, done_s: float = 0.0) -> None:
        """Start with ``part`` clamped in ``mill``'s vise, as the robot's place leaves it: its
        vise output on (the clamp coil and the vise's sensors follow). Call after
        :meth:`start`; a plan takes up a running cell's part where it is so.

        ``done_s``: machine seconds of its cut there already done: the mill's runs on this
        part skip that much of their motion (the emulator's ``head_start_s``; a mill kind
        whose emulator has none cuts it whole)."""
        n = self.mill_names.index(mill) + 1
        if done_s > 0 and hasattr(self.mills[mill], "head_start_s"):
            self._head_start[mill] = (part, done_s)
        port = next(p for p, m in VISE_OUTPUTS.items() if m == n)
        set_output = getattr(self.robot, "set_output", None)
        if set_output is None:
            raise UsageError(
                f"the {self.kinds[self.robot_name]} robot's emulator has no set_output: the "
                f"cell cannot start with a part in {mill}'s vise"
            )
        self.gripper = part
        set_output(port, True)  # the hook moves the part from the gripper into the vise

    def switch_on_at_cut(self, mill: str, name: str, arg: str | None = None) -> None:
        """Switch fault ``name`` of ``mill`` on as the mill's next cut starts (a run with a
        part in its vise), as a fault in the middle of a cut comes: for a fault that acts as
        a block ends (:data:`CUT_FAULTS`), which switched on before the mill's setup block
        would take that block instead. Refused now if the mill's kind has no such switch."""
        if mill not in self.mills:
            raise UsageError(f"{mill!r} is not a mill of this cell ({', '.join(self.mills)})")
        check_switch(registry.kind(self.kinds[mill]).faults, name, arg)
        self._at_cut.setdefault(mill, []).append((name, arg))

    def take_out(self, mill: str) -> str | None:
        """The operator takes the part out of ``mill``'s vise by hand (before scrapping it):
        the part it was, or None. The vise stays as the arm left it: only its output opens
        it."""
        n = self.mill_names.index(mill) + 1
        part, self.vise[n] = self.vise[n], None
        return part

    async def _clear_outfeed(self) -> None:
        clock = self.clock
        await clock.sleep(self.plc.timing.outfeed_s / clock.time_scale)
        self.plc.set_input("outfeed_clear", True)

    def _spawn(self, coro: object) -> None:
        task = asyncio.ensure_future(coro)  # type: ignore[call-overload]
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _noting_cuts(self, index: int, name: str) -> Callable[[Any], None]:
        def note(run: Any) -> None:
            # A run starting on a mill cut whatever part sits in its vise.
            part = self.vise[index]
            self.cuts.append(Cut(name, part, self.clock.now()))
            if part is not None:
                for fault, arg in self._at_cut.pop(name, []):
                    # In the middle of this cut: it acts as the block ends.
                    self.set_fault(name, fault, arg)
            head = self._head_start.get(name)
            if head is None:
                return
            mill = self.mills[name]
            if head[0] != part:
                # Another part's run: what is left of the credit was that cut's only.
                del self._head_start[name]
                mill.head_start_s = 0.0
            elif head[1] > 0:
                # The cut a plan took up mid-way: its runs skip what was done, until spent.
                mill.head_start_s = head[1]
                self._head_start[name] = (part, 0.0)

        return note

    # -- serving ----------------------------------------------------------------------------------

    async def start(self, cell_dir: Path, template: Path | None = None) -> Path:
        """Serve every machine and write ``cell_dir/cell.toml`` pointing at them.

        ``template``: the cell directory to copy (default: the example cell). A
        ``cell_dir/cell.toml`` this did not write (a real cell's) is refused before anything
        is written (:func:`check_cell_dir`); one it wrote is written anew."""
        template = template or self.template
        check_cell_dir(cell_dir)
        # A bare pty gets a stable name in the cell directory, as a serial port has: a
        # dropped connection makes a new pty, and the controller reopens the same path. The
        # directory is resolved, never the link: one left there is replaced, not followed.
        listen = self.robot_listen
        if listen == "pty":
            listen = f"pty:{pty_link_path(str(cell_dir / 'robot.pty'))}"
        claimed = None
        if self.links != "mem" and type(self.robot).listen is EmulatedDevice.listen:
            # A cell already emulated in this directory holds its robot's pty: refused here,
            # before its files are copied over or its cell.toml rewritten (taken, not only
            # looked at: of two starts at once, one is refused before it writes a thing).
            claimed = claim_pty_listen(listen)
        try:
            return await self._start(cell_dir, template, listen, claimed)
        finally:
            if claimed is not None and self.robot_name not in self.servers:
                claimed.release()  # serving never began: nothing holds it

    async def _start(
        self, cell_dir: Path, template: Path, listen: str, claimed: OwnerLock | None
    ) -> Path:
        copy_template(template, cell_dir)
        for index, (name, mill) in enumerate(self.mills.items(), start=1):
            mill.run_hooks.append(self._noting_cuts(index, name))
        self.plc.hooks.input.append(self._plc_input)
        self.robot.output_hooks.append(self._robot_output)
        if self.links == "mem":
            await self._serve_mem()
            return write_text(cell_dir / "cell.toml", self._cell_toml(template / "cell.toml"))
        self.plc_url = await self.plc.start(f"modbus://{self.host}:0")
        for name, value in self.plc.inputs.items():
            self._plc_input(name, value)
        # A robot with interfaces of its own (several ports) serves itself.
        own = await self.robot.listen(self.host)
        if own is not None:
            self.servers[self.robot_name] = own
        else:
            self.servers[self.robot_name] = await serve(
                self.robot,
                listen,
                self.line_of(self.robot_name),
                pacing=self.pacing,
                claimed=claimed,
            )
        for name, mill in self.mills.items():
            self.servers[name] = await serve(
                mill, f"rfc2217://{self.host}:0", self.line_of(name), pacing=self.pacing
            )
            mill.start()
        return write_text(cell_dir / "cell.toml", self._cell_toml(template / "cell.toml"))

    async def _serve_mem(self) -> None:
        """Every machine on ``mem://`` in the running loop, the PLC's Modbus/TCP too."""
        prefix = self.mem_prefix
        self.plc_url = await self.plc.start(f"mem://{prefix}plc")
        for name, value in self.plc.inputs.items():
            self._plc_input(name, value)
        robot_line = self.line_of(self.robot_name)
        # A robot with interfaces of its own serves each on a mem:// name of its own.
        own = await self.robot.listen_mem(f"{prefix}{self.robot_name}", robot_line)
        if own is not None:
            self.servers[self.robot_name] = own
        elif type(self.robot).listen is not EmulatedDevice.listen:
            raise UsageError(
                f"{self.robot_name}: its kind serves interfaces of its own over TCP, which "
                "a mem:// cell cannot carry; emulate this cell on real links"
            )
        else:
            self.servers[self.robot_name] = await serve_mem(
                self.robot, robot_line, name=f"{prefix}{self.robot_name}", pacing=self.pacing
            )
        for name, mill in self.mills.items():
            self.servers[name] = await serve_mem(
                mill, self.line_of(name), name=f"{prefix}{name}", pacing=self.pacing
            )
            mill.start()

    def _cell_toml(self, template: Path) -> str:
        """The template's cell.toml with links, line and timeouts for this emulated cell.

        An emulated cell's file as the template is the real cell's first
        (:func:`real_cell_toml`): one time scale, the real deadlines scaled once. A
        machine's ``[options]`` table of the template is kept, the emulation's options over
        it (one table)."""
        text = real_cell_toml(template.read_text(encoding="utf-8"))
        raw = tomllib.loads(text)
        lines = [
            EMULATED_HEADER.format(scale=self.time_scale),
            "",
        ]
        section = ""
        for line in text.splitlines():
            stripped = line.strip()
            if stripped.startswith("["):
                section = stripped.strip("[] ")
            if is_options(section):
                continue  # written below, with the emulation's options
            key = stripped.split("=", 1)[0].strip() if "=" in stripped else ""
            if section.startswith("machines.") and key == "link":
                name = section.split(".", 1)[1]
                line = f'link = "{self.servers[name].url}"'
            elif section.startswith("machines.") and key == "line":
                line = f'line = "{self.line_of(section.split(".", 1)[1])}"'
            elif section == "plc" and key == "url":
                line = f'url = "{self.plc_url}"'
            elif section == "cell" and key in CELL_DEADLINES:
                # A deadline for a machine's work (a pallet, a door, a transfer) scales with
                # the machines' time as the mills' do below.
                value = float(raw["cell"][key])
                scaled = scaled_deadline(value, self.time_scale)
                line = f"{key} = {scaled:g}" + DEADLINE_NOTE.format(real=value)
            lines.append(line)
            if stripped == "[cell]":
                lines.append(f"time_scale = {self.time_scale:g}  # the machines' time, x real")
        scale = self.time_scale
        # Deadlines scale with the machines' time; a real cell keeps the template's.
        for name, machine in raw.get("machines", {}).items():
            kind = registry.kind(machine.get("kind"))
            options: dict[str, int | float | str] = dict(machine.get("options", {}))
            served = self.servers.get(name)
            if isinstance(served, SelfServed):
                options.update(served.options)
            if kind.emulated_options:
                emulated = kind.emulated_options(scale)
                if scale == 1.0:
                    # The machines' own time (a plan): the cell's options are the real cell's,
                    # played as they are; the kind's fill only what the cell leaves unset.
                    emulated = {k: v for k, v in emulated.items() if k not in options}
                options.update(emulated)
            if options:
                lines += ["", f"[machines.{name}.options]"]
                lines += [f"{key} = {_toml(value)}" for key, value in options.items()]
        return "\n".join(lines) + "\n"

    def line_of(self, name: str) -> LineSettings:
        """The line machine ``name`` is served on (the base line for one of no known kind)."""
        return self.lines.get(name, self.line)

    def runs_per_part(self) -> dict[str, dict[str, int]]:
        """How many programs each mill ran per physical part (from the emulators' logs).

        Runs with an empty vise (setup programs) are not counted.
        """
        out: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
        for cut in self.cuts:
            if cut.part is not None:
                out[cut.part][cut.mill] += 1
        return {k: dict(v) for k, v in out.items()}

    async def close(self) -> None:
        """Stop every server and the PLC."""
        await cancel_and_wait(self._tasks)
        for server in self.servers.values():
            await server.close()
        for device in (self.robot, *self.mills.values()):
            await device.stop()
        await self.plc.close()


def _toml(value: int | float | str) -> str:
    return f"{value:g}" if isinstance(value, int | float) else f'"{value}"'


def scaled_line(line: LineSettings, time_scale: float) -> LineSettings:
    """``line`` with its baud rate ``time_scale`` times higher (characters as much faster)."""
    return LineSettings(
        int(line.baudrate * time_scale), line.bytesize, line.parity, line.stopbits, line.rtscts
    )


def _machine_kinds(template: Path) -> dict[str, str]:
    """The machines of ``template``'s cell.toml and their kinds."""
    path = template / "cell.toml"
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise UsageError(f"{path}: cannot read it: {e}") from None
    machines = raw.get("machines", {})
    kinds = {
        name: entry["kind"]
        for name, entry in machines.items()
        if isinstance(entry, dict) and isinstance(entry.get("kind"), str)
    }
    for kind in set(kinds.values()) - set(registry.names()):
        with contextlib.suppress(UsageError):  # unknown: cell check names it (BrokenKind: here)
            registry.kind(kind)
    return {name: kind for name, kind in kinds.items() if kind in registry.names()}


def check_cell_dir(cell_dir: Path) -> None:
    """UsageError if ``cell_dir`` holds a cell.toml an emulated cell did not write: a real
    cell's configuration, which emulating there would overwrite (with its programs). Reads
    only: called before anything is copied or written."""
    toml = cell_dir / "cell.toml"
    if not (toml.exists() or toml.is_symlink()) or written_by_emulation(toml):
        return
    raise UsageError(
        f"{toml} was not written by cellctl emulate cell (its first line is not "
        "'# Emulated cell (time scale ...)'): emulating here would overwrite it and the "
        f"programs beside it. Emulate in another directory (--cell DIR), with --template "
        f"{cell_dir} to serve this cell's machines; or delete {toml} first"
    )


def copy_template(template: Path, cell_dir: Path) -> None:
    """Copy a cell's programs (``robot/``, ``programs/``) from ``template`` to ``cell_dir``."""
    if not (template / "cell.toml").is_file():
        raise UsageError(f"{template}: no cell.toml to copy")
    cell_dir.mkdir(parents=True, exist_ok=True)
    for sub in ("robot", "programs"):
        if (template / sub).is_dir():
            shutil.copytree(template / sub, cell_dir / sub, dirs_exist_ok=True)


def write_text(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` and return the path."""
    path.write_text(text, encoding="utf-8")
    return path
