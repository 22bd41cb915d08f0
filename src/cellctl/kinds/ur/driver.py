"""Driver for a Universal Robots arm (CB3, e-Series): the robot family over three TCP links.

- the **Dashboard Server** (``link``, the cell's ``socket://HOST:29999``): power on, brake
  release, load, play, pause, stop, and every refusal in UR's words;
- **RTDE** (``HOST:rtde_port``): the robot's state streamed at ``rtde_frequency``; a minimal
  asyncio client of the public protocol (:mod:`cellctl.kinds.ur.rtde_client`, over the
  codecs of :mod:`cellctl.kinds.ur.rtde`);
- the **secondary interface** (``HOST:secondary_port``): a URScript program from the cell,
  sent whole; it replaces what runs.

Why not ``ur-rtde``'s RTDEReceiveInterface: it is a C++ client with a thread of its own
per robot, whose Python binding blocks the interpreter while it connects (the GIL is held
through the handshake). The cell controller drives every machine on one asyncio loop, with
a deadline on every wait; an RTDE client here is a coroutine reading a socket, ~100 lines
over the same codec the emulator speaks. ur-rtde stays the independent client the tests
check the emulator with.

::

    robot = await UrRobot.connect("socket://192.168.1.10:29999", options=UrOptions())
    await robot.initialize()                 # power on, brake release, RUNNING (a deadline each)
    slot = await robot.ensure_program("tend_cnc1", program)
    await robot.start(slot)
    await robot.wait_end(0, timeout=120)     # its end: RTDE runtime state / its end register
    status = await robot.status()            # robot mode, safety status, program state, I/O

``unlock_protective_stop()`` is never called by the driver itself: the operator calls it
(the menu's ``robot.unlock``) after inspecting the cause.
"""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from cellctl.clock import Clock
from cellctl.drivers.base import LinkDriver
from cellctl.drivers.state import StateStore
from cellctl.errors import (
    CellctlError,
    DeviceError,
    LinkError,
    ProtocolError,
    SignalTimeout,
    UnexpectedReply,
    UsageError,
)
from cellctl.files import read_text, reason
from cellctl.kinds.condition import Condition
from cellctl.kinds.families import CycleAborted, HostStatus, RecordsProgress
from cellctl.kinds.ur import rtde
from cellctl.kinds.ur.dashboard import (
    BANNER,
    COMMANDS,
    MOVING_SAFETY,
    RobotMode,
    RuntimeState,
)
from cellctl.kinds.ur.motion import ARMS
from cellctl.kinds.ur.options import INTERFACE_PORTS, UR_SCHEMES, interface_url, link_ports
from cellctl.kinds.ur.options import UR_LINE as UR_LINE
from cellctl.kinds.ur.options import UrOptions as UrOptions
from cellctl.kinds.ur.program import UrProgram
from cellctl.kinds.ur.rtde_client import FIELDS as FIELDS
from cellctl.kinds.ur.rtde_client import RtdeClient, UrStatus, _State
from cellctl.link import LineSettings, Link, TrafficLog, open_link

# UR_LINE and UrOptions live in options.py (the registry reads them without importing this
# driver), FIELDS and UrStatus in rtde_client.py with the RTDE client: all named here as before.


class UrRefused(DeviceError):
    """The Dashboard Server refused a command: ``message`` is its answer, in UR's words."""

    def __init__(self, command: str, answer: str, detail: str) -> None:
        super().__init__(0, answer, detail=detail)
        self.command = command
        # The Dashboard Server has no result codes: its answer and the command, not a "code 0".
        self.args = (f"{detail} (the robot answered {answer!r} to {command!r})",)

    def __str__(self) -> str:
        return str(self.args[0])


class LocalMode(UrRefused):
    """An e-Series pendant in local mode: nothing but the pendant may act."""


class UrStopped(CycleAborted):
    """A program stopped by the robot: a safety stop, the power gone; ``status`` says it."""


class UrRobot(RtdeClient, LinkDriver):
    """One UR controller (see module docstring); ``link`` is its Dashboard Server."""

    def __init__(
        self,
        link: Link,
        *,
        name: str | None = None,
        store: StateStore | None = None,
        options: UrOptions | None = None,
        trace: TrafficLog | None = None,
        clock: Clock | None = None,
    ) -> None:
        saved = self._attach(link, name, store, clock)
        self.options = options or UrOptions()
        self.arm = ARMS[self.options.model]
        self.trace = trace
        self.initialized = bool(saved.get("initialized", False))
        self._running = False
        self._programs: list[UrProgram] = []
        self._current: UrProgram | None = None
        self._seq = 0
        self._started_at = 0.0
        self._played = False  # the program started was seen playing (kept across waits)
        self._dashboard_lock = asyncio.Lock()
        self._state = _State()
        self._changed = asyncio.Event()
        self._rtde: Link | None = None
        self._secondary: Link | None = None
        self._reader: asyncio.Task[None] | None = None
        self.version: rtde.ControllerVersion | None = None
        self.rtde_error: CellctlError | None = None

    @classmethod
    async def connect(
        cls,
        url: str,
        *,
        name: str | None = None,
        settings: LineSettings | None = None,
        store: StateStore | None = None,
        options: UrOptions | None = None,
        trace: TrafficLog | None = None,
        clock: Clock | None = None,
    ) -> UrRobot:
        """Open the Dashboard Server at ``url`` (``socket://HOST:PORT``; ``mem://NAME`` for an
        emulator in this event loop), then RTDE beside it; MachineInUse before anything
        opens when another owner holds the robot."""
        if urlsplit(url).scheme not in UR_SCHEMES:
            raise UsageError(f"{url}: a UR's link is its Dashboard Server, socket://HOST:29999")
        dashboard, ports = link_ports(url)
        options = _with_ports(options or UrOptions(), ports, url)
        robot = await cls._connect_owned(
            dashboard,
            settings or LineSettings.parse(UR_LINE),
            name=name,
            store=store,
            trace=trace,
            build=lambda link: cls(link, name=name or url, store=store, options=options,
                                   trace=trace, clock=clock),
            clock=clock,
        )  # fmt: skip
        try:
            await robot._open()
        except BaseException:
            await robot.close()
            raise
        return robot

    async def _open_interface(self, interface: str, port: int) -> Link:
        """A link to the UR's ``interface`` (``rtde``, ``secondary``), beside its Dashboard
        Server; LinkError naming the interface, its port and how to give another."""
        url = interface_url(self.link.url, interface, port)
        try:
            return await open_link(
                url, self.link.settings,
                trace=self.trace, label=f"{self.name}-{interface}", clock=self.clock,
            )  # fmt: skip
        except LinkError as e:
            if urlsplit(url).scheme == "mem":
                raise
            key = f"{interface}_port"
            title = INTERFACE_PORTS[key]
            raise LinkError(
                f"{self.name}: the UR's {title} at port {port} cannot be reached ({e}), though "
                f"its Dashboard Server answered at {self.link.url}; if {title} listens at "
                f"another port, give it: --link '{self.link.url}?{key}=PORT', or {key} = PORT "
                "in the machine's options in cell.toml"
            ) from e

    async def _open(self) -> None:
        banner = await self._line(self.options.reply_timeout)
        if banner != BANNER:
            raise UnexpectedReply(f"{self.name}: not a Dashboard Server: {banner!r}")
        self._rtde = await self._open_interface("rtde", self.options.rtde_port)
        await self._rtde_handshake(self._rtde)
        self._reader = asyncio.ensure_future(self._read_rtde(self._rtde))
        await self._wait_state(lambda s: True, self.options.state_timeout, "a first RTDE package")

    async def close(self) -> None:
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(BaseException):
                await self._reader
        for extra in (self._rtde, self._secondary):
            if extra is not None:
                with contextlib.suppress(CellctlError, OSError):
                    await extra.close()
        await super().close()

    def _save(self) -> None:
        self._persist({"initialized": self.initialized})

    # -- the Dashboard Server ---------------------------------------------------------------------

    async def _line(self, timeout: float) -> str:
        raw = await self.link.read_until(b"\n", timeout=timeout)
        try:
            return raw.decode("utf-8").strip()
        except UnicodeDecodeError:
            raise ProtocolError(f"{self.name}: Dashboard answer is not UTF-8", raw) from None

    async def ask(self, line: str) -> str:
        """One Dashboard Server line and its answer (as it came)."""
        if "\n" in line or "\r" in line or not line.strip():
            raise UsageError(f"a Dashboard Server command is one line, not {line!r}")
        async with self._dashboard_lock:
            self.link.reset_input()
            await self.link.write(line.encode("utf-8") + b"\n")
            return await self._line(self.options.reply_timeout)

    async def command(self, text: str, arg: str = "") -> str:
        """Send a command of :data:`COMMANDS`; UrRefused with its answer unless it succeeded."""
        spec = COMMANDS[text]
        answer = await self.ask(f"{text} {arg}".strip())
        if not spec.ok(answer, arg):
            raise UrRefused(text, answer, f"{self.name}: {text} refused")
        return answer

    async def remote_control(self) -> bool | None:
        """``is in remote control``: None on a controller that does not know it (a CB3)."""
        answer = await self.ask("is in remote control")
        return {"true": True, "false": False}.get(answer)

    async def require_remote(self) -> None:
        """LocalMode (before anything acts) when an e-Series pendant is in local mode."""
        if await self.remote_control() is False:
            raise LocalMode(
                "is in remote control",
                "false",
                f"{self.name}: the pendant is in local mode: switch it to remote control "
                "(the pendant's top bar) before the cell can act",
            )

    # -- the robot family (cellctl.kinds.families.Robot) ------------------------------------------

    @property
    def running(self) -> bool:
        return self._running

    @property
    def ready(self) -> bool:
        return self.initialized and not self._running and self._latest_ok()

    @property
    def cold(self) -> bool:
        return not self.initialized or not self._latest_ok()

    def _latest_ok(self) -> bool:
        values = self._state.values
        return bool(values) and self._status_of(values).ok

    def host_status(self) -> HostStatus:
        """The latest RTDE state in UR's words and its condition (no byte sent)."""
        if not self._state.values:
            return HostStatus("no RTDE data", Condition.OFFLINE)
        status = self._status_of(self._state.values)
        return HostStatus(str(status), status.condition)

    def needs_initialize(self, error: DeviceError) -> bool:
        return self.cold

    async def initialize(self) -> None:
        """Power on and release the brakes until robot mode RUNNING, a deadline each.

        Refused in UR's words: local mode (LocalMode), a safety stop (UrRefused naming it:
        the operator inspects and unlocks it), a command the controller refuses."""
        await self.require_remote()
        status = self._status_of(self._fresh())
        if status.safety not in MOVING_SAFETY:
            raise UrRefused(
                "safetystatus",
                f"Safetystatus: {status.safety.text}",
                f"{self.name}: cannot initialize in a safety stop: the operator inspects the "
                "cause, then unlocks or releases it",
            )
        if status.mode in (RobotMode.POWER_OFF, RobotMode.CONFIRM_SAFETY, RobotMode.BOOTING):
            await self.command("power on")
            await self._wait_state(
                lambda s: s.mode in (RobotMode.IDLE, RobotMode.RUNNING),
                self.options.power_on_timeout,
                "Robotmode: IDLE after power on",
            )
        status = self._status_of(self._fresh())
        if status.mode != RobotMode.RUNNING:
            await self.command("brake release")
            await self._wait_state(
                lambda s: s.mode == RobotMode.RUNNING,
                self.options.brake_release_timeout,
                "Robotmode: RUNNING after brake release",
            )
        self.initialized = True
        self._save()

    async def ensure_program(
        self, name: str, program: Any, progress: RecordsProgress | None = None
    ) -> int:
        """Where ``program`` (a :class:`UrProgram`) is known: checked against this arm's
        model first (UsageError with each problem before a byte goes out)."""
        if not isinstance(program, UrProgram):
            raise UsageError(f"{self.name}: {name} is not a UR program")
        problems = program.problems(self.arm)
        if problems:
            raise UsageError(f"{self.name}: {name}: " + "; ".join(problems))
        # Nothing goes out here: a script is sent whole as it starts, a .urp is on the robot.
        if program not in self._programs:
            self._programs.append(program)
        return self._programs.index(program)

    async def start(self, slot: int) -> None:
        """Run program ``slot``: a ``.urp`` by ``load`` and ``play``, a script on the
        secondary interface (its end register added). Refused first when the arm cannot."""
        if not 0 <= slot < len(self._programs):
            raise UsageError(f"{self.name}: no program in slot {slot}")
        program = self._programs[slot]
        await self.require_remote()
        status = self._status_of(self._fresh())
        if not status.ok:
            raise UrRefused("play", str(status), f"{self.name}: cannot start {program.name}")
        if program.on_robot:
            loaded = await self.ask("get loaded program")
            if loaded != f"Loaded program: {program.path}":
                await self.command("load", program.path)
            await self.command("play")
        else:
            self._seq = (self._state.values.get(self._end_field(), 0) + 1) % 2**31 or 1
            text = program.sendable(self.options.end_register, self._seq)
            if self._secondary is None or self._secondary.closed:
                self._secondary = await self._open_interface(
                    "secondary", self.options.secondary_port
                )
            await self._secondary.write(text.encode("utf-8"))
        self._started_at = self.clock.monotonic()
        self._played = False
        self._current = program
        self._running = True

    def _end_field(self) -> str:
        return f"output_int_register_{self.options.end_register}"

    async def wait_end(
        self,
        done_output: int,
        *,
        timeout: float,
        poll: float = 0.1,
        watch_every: float = 0.0,
        expected: float = 0.0,
    ) -> None:
        """Wait for the program's end (RTDE: runtime state STOPPED after it played, or its
        end register); UrStopped when a safety stop or the power stopped it, in UR's words.

        ``done_output`` and ``expected`` are not needed: a UR says when its program ends."""
        program = self._current
        if program is None:
            raise UsageError(f"{self.name}: no program was started")
        deadline = self.clock.monotonic() + timeout
        period = 1.0 / self.options.rtde_frequency
        started = self._started_at
        by_register = not program.on_robot and self.options.end_register is not None
        while True:
            values = self._fresh()
            status = self._status_of(values)
            fresh = self._state.at > started + 2 * period
            if not status.ok and fresh:
                self._running = False
                raise UrStopped(status, f"{self.name}: {program.name} stopped by the robot")
            if by_register and values.get(self._end_field()) == self._seq:
                break
            if status.runtime == RuntimeState.PLAYING:
                self._played = True  # a wait cut short and asked again still knows it
            played = self._played
            if fresh and status.runtime == RuntimeState.STOPPED and (played or program.on_robot):
                break
            if (
                not played
                and not program.on_robot
                and self.clock.monotonic() > started + self.options.start_timeout
            ):
                self._running = False
                raise UrRefused(
                    "secondary interface",
                    str(status),
                    f"{self.name}: {program.name} did not start within "
                    f"{self.options.start_timeout:g} s of being sent",
                )
            left = deadline - self.clock.monotonic()
            if left <= 0:
                raise SignalTimeout(
                    f"{self.name}: {program.name} did not end within {timeout:g} s "
                    f"(programState {status.runtime.text})"
                )
            self._changed.clear()
            with contextlib.suppress(TimeoutError):
                async with self.clock.timeout(min(left, self.options.state_timeout)):
                    await self._changed.wait()
        self._running = False

    async def machine_status(self) -> UrStatus:
        """The latest RTDE state (LinkTimeout when the stream stopped)."""
        return self._status_of(self._fresh())

    async def status(self) -> UrStatus:
        """The RTDE state with the Dashboard Server's loaded program and remote control."""
        base = self._status_of(self._fresh())
        loaded = await self.ask("get loaded program")
        remote = await self.remote_control()
        path = loaded.removeprefix("Loaded program: ") if loaded.startswith("Loaded") else None
        return UrStatus(base.mode, base.safety, base.runtime, base.inputs, base.outputs, base.q,
                        path, remote)  # fmt: skip

    async def stop(self) -> None:
        """``stop``: whatever runs stops (a script too)."""
        await self.command("stop")
        self._running = False

    async def pause(self) -> None:
        await self.require_remote()
        await self.command("pause")

    async def resume(self) -> None:
        """``play`` a paused program again."""
        await self.require_remote()
        await self.command("play")

    async def reset_errors(self) -> None:
        """``close popup``: what the cell may do by itself. A protective stop is the
        operator's (:meth:`unlock_protective_stop`), never done here."""
        await self.command("close popup")

    async def unlock_protective_stop(self) -> None:
        """The operator's explicit action after inspecting the cause (UR refuses it within
        5 s of the stop, in its words)."""
        await self.require_remote()
        await self.command("unlock protective stop")

    async def close_safety_popup(self) -> None:
        await self.command("close safety popup")

    async def power_off(self) -> None:
        await self.require_remote()
        await self.command("power off")
        self.initialized = False
        self._save()


def _with_ports(options: UrOptions, ports: dict[str, int], url: str) -> UrOptions:
    """``options`` with the interface ports the link URL gives; UsageError when an option
    set in cell.toml says another port."""
    for key, port in ports.items():
        if key in options.model_fields_set and getattr(options, key) != port:
            raise UsageError(
                f"{url}: {key} {port} in the link URL, {getattr(options, key)} in the options: "
                "give it once"
            )
    return options.model_copy(update=ports) if ports else options


def read_program(path: Path) -> str:
    """A program file's text (UsageError when it cannot be read)."""
    try:
        return read_text(path)
    except (OSError, UnicodeDecodeError) as e:
        raise UsageError(f"{path}: cannot read it: {reason(e)}") from None


__all__ = [
    "FIELDS",
    "LinkError",
    "LocalMode",
    "UrOptions",
    "UrRefused",
    "UrRobot",
    "UrStatus",
    "UrStopped",
]
