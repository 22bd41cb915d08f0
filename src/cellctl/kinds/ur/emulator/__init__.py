"""A Universal Robots controller, emulated: the Dashboard Server, the secondary interface
and RTDE on loopback (any ports), over one :class:`~.controller.UrController`::

    emulator = UrEmulator(time_scale=10.0, programs={"/programs/tend.urp": SCRIPT})
    ports = await emulator.start("127.0.0.1")   # {"dashboard": 41234, "secondary": ..., ...}
    emulator.set_fault("protective_stop")
    ...
    await emulator.close()

- Dashboard Server: the banner, then one answer line per command line (UR's words,
  :data:`cellctl.kinds.ur.dashboard.COMMANDS`).
- Secondary interface: URScript text; a whole program (``def ... end``, or one line outside
  any ``def``) runs at once, replacing what runs. The controller's binary state stream on
  this port is not emulated (the driver reads state through RTDE).
- RTDE: protocol versions 1 and 2, the controller's version, output and input recipes
  (``NOT_FOUND`` for a field it does not offer, ``IN_USE`` for an input another client
  holds), start and pause, data packages at the recipe's frequency (at most 500 Hz on an
  e-Series, 125 Hz on a CB3), input packages (digital outputs, integer registers).

It is also an :class:`~cellctl.emulators.serve.EmulatedDevice`: ``serve(emulator,
"socket://...")`` puts its Dashboard Server on one line, as other kinds' emulators are served.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
from typing import Any

from cellctl.clock import Clock
from cellctl.emulators.memserve import serve_mem_streams
from cellctl.emulators.serve import DeviceLine, EmulatedDevice, SelfServed
from cellctl.errors import ProtocolError, UsageError
from cellctl.kinds.ur import rtde
from cellctl.kinds.ur.dashboard import (
    BANNER,
    MAX_ANSWER,
    RobotMode,
    RuntimeState,
    SafetyStatus,
)
from cellctl.kinds.ur.emulator.controller import FAULTS, UrController
from cellctl.kinds.ur.options import mem_interface
from cellctl.kinds.ur.urscript import parse
from cellctl.link import LineSettings
from cellctl.link.mem import MemListener

__all__ = ["FAULTS", "UrController", "UrEmulator"]

#: Longest script the secondary interface takes in one program, bytes.
MAX_SCRIPT = 1_000_000


#: RTDE's frequency, Hz, a cell in one event loop (a plan's) asks of the emulator: its
#: robot's state every 0.1 s, so a program's end is seen at most that late (a plan's
#: schedule moves by tenths of a second a transfer). At the robot's own 125 Hz a plan's hour
#: would be 450,000 packages, many times the rest of the cell's work.
MEM_RTDE_HZ = 10.0
#: The operator at the pendant after a fault: seconds between two looks, and how many looks at
#: most (an unlock 5 s after the stop, power on 2 s, brake release 1.5 s).
PENDANT_WAIT_S = 1.0
PENDANT_TRIES = 30


class UrEmulator(EmulatedDevice):
    """The three interfaces over one controller (see module docstring)."""

    def __init__(self, **controller: Any) -> None:
        self.controller = UrController(**controller)
        self.ports: dict[str, int] = {}
        self.host = "127.0.0.1"
        self._servers: list[asyncio.Server] = []
        self._mem: list[MemListener] = []
        self._writers: set[asyncio.StreamWriter] = set()
        self._tasks: set[asyncio.Task[Any]] = set()
        self._held_inputs: dict[str, object] = {}  # RTDE input field -> the client holding it
        self.controller.on_drop.append(self.drop)
        self.rtde_sent = 0

    @property
    def clock(self) -> Clock:
        """The controller's clock (given as ``clock=`` or ``time_scale=``)."""
        return self.controller.clock

    @property
    def time_scale(self) -> float:
        return self.controller.time_scale

    @time_scale.setter
    def time_scale(self, value: float) -> None:
        self.controller.time_scale = value

    # the emulated cell's wiring and fault switches, as other robot emulators have them
    @property
    def output_hooks(self) -> Any:
        return self.controller.output_hooks

    def set_input(self, n: int, value: bool | int) -> None:
        self.controller.set_input(n, value)

    def set_output(self, n: int, value: bool) -> None:
        self.controller.set_digital_out(n, value)

    def set_fault(self, name: str, arg: str | None = None) -> None:
        self.controller.set_fault(name, arg)

    @property
    def faults(self) -> dict[str, str | None]:
        """The switches on now, each with its argument (None: none given)."""
        return dict(self.controller.faults)

    def clear_fault(self, name: str) -> None:
        self.controller.clear_fault(name)

    async def operator_after(self, fault: str) -> None:
        """The operator at the pendant brings the arm back to RUNNING: a protective stop
        unlocked (UR refuses within 5 s of the stop: the operator waits them out), the power
        on, the brakes released. The paused or stopped program is left to the host."""
        controller = self.controller
        for _ in range(PENDANT_TRIES):
            if controller.safety is SafetyStatus.PROTECTIVE_STOP:
                controller.answer("unlock protective stop")
            elif controller.mode is RobotMode.POWER_OFF:
                controller.answer("power on")
            elif controller.mode is RobotMode.IDLE:
                controller.answer("brake release")
            elif controller.mode is RobotMode.RUNNING:
                return
            await self.clock.sleep(PENDANT_WAIT_S)
        raise UsageError(
            f"the operator could not bring the robot back: Robotmode {controller.mode.name}, "
            f"Safetystatus {controller.safety.name}"
        )

    @property
    def moving(self) -> bool:
        """The arm moves while the controller plays a program."""
        return self.controller.runtime is RuntimeState.PLAYING

    # -- serving ----------------------------------------------------------------------------------

    async def start(
        self, host: str = "127.0.0.1", *, dashboard: int = 0, secondary: int = 0, rtde_port: int = 0
    ) -> dict[str, int]:
        """Listen on ``host``: the three interfaces' ports (0: a free one each)."""
        self.host = host
        for name, port, handler in (
            ("dashboard", dashboard, self._dashboard),
            ("secondary", secondary, self._secondary),
            ("rtde", rtde_port, self._rtde),
        ):
            server = await asyncio.start_server(self._tracked(handler), host, port)
            self._servers.append(server)
            self.ports[name] = server.sockets[0].getsockname()[1]
        return dict(self.ports)

    async def listen(self, host: str) -> SelfServed:
        """Serve the three interfaces on free ports of ``host`` (the emulated cell)."""
        ports = await self.start(host)
        options: dict[str, int | float | str] = {
            "secondary_port": ports["secondary"],
            "rtde_port": ports["rtde"],
        }
        return SelfServed(self.dashboard_url, options, self.close)

    async def listen_mem(self, name: str, settings: LineSettings) -> SelfServed:
        """Serve the three interfaces in the running event loop: the Dashboard Server at
        ``mem://name``, the others beside it (``mem://name.rtde``, ``mem://name.secondary``:
        :func:`~cellctl.kinds.ur.options.mem_interface`). RTDE streams at
        :data:`MEM_RTDE_HZ` there (the cell's option)."""
        for where, handler in (
            (name, self._dashboard),
            (mem_interface(name, "secondary"), self._secondary),
            (mem_interface(name, "rtde"), self._rtde),
        ):
            self._mem.append(serve_mem_streams(where, settings, self._tracked(handler)))
        return SelfServed(f"mem://{name}", {"rtde_frequency": MEM_RTDE_HZ}, self.close)

    @property
    def dashboard_url(self) -> str:
        """What a cell's ``link`` names: the Dashboard Server."""
        return f"socket://{self.host}:{self.ports['dashboard']}"

    def _tracked(self, handler: Any) -> Any:
        async def run(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            self._writers.add(writer)
            task = asyncio.current_task()
            if task is not None:
                self._tasks.add(task)
            try:
                await handler(reader, writer)
            except (ConnectionError, asyncio.IncompleteReadError, ProtocolError):
                pass
            finally:
                self._writers.discard(writer)
                if task is not None:
                    self._tasks.discard(task)
                writer.close()
                with contextlib.suppress(Exception):
                    await writer.wait_closed()

        return run

    def drop(self) -> None:
        """Close every client connection now (the ``drop`` fault)."""
        for writer in list(self._writers):
            transport = writer.transport
            transport.abort()

    async def close(self) -> None:
        for server in self._servers:
            server.close()
        for listener in self._mem:
            listener.close()
        self.drop()
        # Aborted connections end their handlers by themselves (a cancelled handler is
        # logged by asyncio's server as an error); one that lingers is cancelled.
        if self._tasks:
            _, lingering = await asyncio.wait(list(self._tasks), timeout=2.0)
            for task in lingering:
                task.cancel()
        for server in self._servers:
            with contextlib.suppress(Exception):
                await server.wait_closed()
        await self.controller.close()

    # -- Dashboard Server -------------------------------------------------------------------------

    async def _dashboard(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(BANNER.encode() + b"\n")
        while True:
            raw = await reader.readline()
            if not raw:
                return
            line = raw[:MAX_ANSWER].decode("utf-8", "replace").strip()
            answer = self.controller.answer(line)
            writer.write(answer.encode("utf-8") + b"\n")
            await writer.drain()
            if answer == "Disconnected":
                return

    async def session(self, line: DeviceLine) -> None:
        """The Dashboard Server on one served line (``serve(emulator, "socket://...")``)."""
        await line.write(BANNER.encode() + b"\n")
        while True:
            raw = await line.read_until(b"\n")
            answer = self.controller.answer(raw[:MAX_ANSWER].decode("utf-8", "replace").strip())
            await line.write(answer.encode("utf-8") + b"\n")

    # -- secondary interface ----------------------------------------------------------------------

    async def _secondary(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        pending: list[str] = []
        depth = 0
        while True:
            raw = await reader.readline()
            if not raw:
                return
            text = raw.decode("utf-8", "replace")
            stripped = text.split("#", 1)[0].strip()
            pending.append(text)
            if sum(len(p) for p in pending) > MAX_SCRIPT:
                pending, depth = [], 0
                continue
            if stripped.startswith(("def ", "while ", "if ", "thread ")):
                depth += 1
            elif stripped == "end":
                depth -= 1
            if depth <= 0 and any(p.strip() for p in pending):
                program = "".join(pending)
                pending, depth = [], 0
                if parse(program).problems:
                    self.controller.messages.append("script refused: it does not parse")
                    continue
                self.controller.script(program)

    # -- RTDE -------------------------------------------------------------------------------------

    async def _rtde(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        session = _RtdeSession(self, writer)
        try:
            while True:
                header = await reader.readexactly(rtde.HEADER.size)
                size, _ = rtde.HEADER.unpack(header)
                if size < rtde.HEADER.size:
                    raise ProtocolError("RTDE packet size below its header's", header)
                body = await reader.readexactly(size - rtde.HEADER.size)
                packet_type, payload, _ = rtde.decode(header + body)
                await session.handle(packet_type, payload)
        finally:
            session.stop()
            for name, holder in list(self._held_inputs.items()):
                if holder is session:
                    del self._held_inputs[name]


class _RtdeSession:
    """One RTDE client: its version, recipes and stream."""

    def __init__(self, emulator: UrEmulator, writer: asyncio.StreamWriter) -> None:
        self.emulator = emulator
        self.writer = writer
        self.version = 1
        self.next_id = 1
        self.output: rtde.Recipe | None = None
        self.frequency = 125.0
        self.inputs: dict[int, rtde.Recipe] = {}
        self.stream: asyncio.Task[None] | None = None

    def send(self, packet_type: int, payload: bytes) -> None:
        self.writer.write(rtde.encode(packet_type, payload))

    async def handle(self, packet_type: int, payload: bytes) -> None:
        controller = self.emulator.controller
        t = rtde.PacketType
        if packet_type == t.REQUEST_PROTOCOL_VERSION:
            wanted = rtde.parse_request_protocol_version(payload)
            accepted = wanted in rtde.PROTOCOL_VERSIONS
            if accepted:
                self.version = wanted
            self.send(t.REQUEST_PROTOCOL_VERSION, rtde.protocol_version_reply(accepted))
        elif packet_type == t.GET_URCONTROL_VERSION:
            self.send(t.GET_URCONTROL_VERSION, rtde.controller_version_reply(controller.version))
        elif packet_type == t.SETUP_OUTPUTS:
            frequency, names = rtde.parse_setup_outputs(payload, self.version)
            limit = controller.version.max_frequency
            if frequency is not None and not 0 < frequency <= limit:
                self.send(
                    t.TEXT_MESSAGE,
                    rtde.text_message(f"frequency {frequency:g} Hz: it must be 0 < f <= {limit:g}"),
                )
                recipe = rtde.Recipe(0, tuple(names), tuple(rtde.NOT_FOUND for _ in names))
            else:
                recipe = rtde.recipe_for(self._id(), names, rtde.OUTPUTS)
                self.frequency = frequency or limit
                if recipe.ok:
                    self.output = recipe
            self.send(t.SETUP_OUTPUTS, rtde.setup_reply(recipe, self.version))
        elif packet_type == t.SETUP_INPUTS:
            names = rtde.parse_setup_inputs(payload)
            held = self.emulator._held_inputs
            in_use = frozenset(n for n in names if held.get(n, self) is not self)
            recipe = rtde.recipe_for(self._id(), names, rtde.INPUTS, in_use)
            if recipe.ok:
                self.inputs[recipe.recipe_id] = recipe
                for n in names:
                    held[n] = self
            self.send(t.SETUP_INPUTS, rtde.setup_reply(recipe, self.version))
        elif packet_type == t.START:
            accepted = self.output is not None or bool(self.inputs)
            if accepted and self.output is not None and self.stream is None:
                self.stream = asyncio.ensure_future(self._stream(self.output))
            self.send(t.START, rtde.start_reply(accepted))
        elif packet_type == t.PAUSE:
            self.stop()
            self.send(t.PAUSE, rtde.start_reply(True))
        elif packet_type == t.DATA_PACKAGE:
            recipe_id = payload[0] if self.version >= 2 and payload else 0
            found = self.inputs.get(recipe_id) or (
                next(iter(self.inputs.values()), None) if self.version < 2 else None
            )
            if found is None:
                self.send(t.TEXT_MESSAGE, rtde.text_message(f"no input recipe {recipe_id}"))
                return
            controller.take_inputs(rtde.unpack_data(found, payload, self.version))
        else:
            self.send(t.TEXT_MESSAGE, rtde.text_message(f"unknown packet type {packet_type}"))
        await self.writer.drain()

    def _id(self) -> int:
        recipe_id, self.next_id = self.next_id, self.next_id % 255 + 1
        return recipe_id

    def stop(self) -> None:
        if self.stream is not None:
            self.stream.cancel()
            self.stream = None

    async def _stream(self, recipe: rtde.Recipe) -> None:
        # Package k is due at start + k/frequency: absolute deadlines, so a late wake-up
        # never shifts the ones after it (no drift). A package the loop is late for goes out
        # at once, never skipped: its ``timestamp`` is its controller cycle's (start + k
        # periods, as a real controller stamps the cycle it sampled), so a client counts a
        # missing package by its timestamp and never mistakes the loop's jitter for one.
        period = 1.0 / self.frequency
        clock = self.emulator.clock
        controller = self.emulator.controller
        start = clock.monotonic()
        stamp0 = start - controller.started_at
        k = 0
        try:
            while True:
                values = controller.sample()
                values["timestamp"] = stamp0 + k * period
                payload = rtde.pack_data(recipe, values, self.version)
                self.writer.write(rtde.encode(rtde.PacketType.DATA_PACKAGE, payload))
                self.emulator.rtde_sent += 1
                k += 1
                delay = start + k * period - clock.monotonic()
                if delay > 0:
                    await clock.sleep(delay)
                elif k % 32 == 0:
                    await clock.sleep(0)  # a long catch-up still lets the loop breathe
        except (ConnectionError, struct.error):
            return
