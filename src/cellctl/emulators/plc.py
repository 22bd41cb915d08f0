"""The cell's PLC, emulated: a Modbus/TCP server over a small model of the cell's hardware.

Serve it and drive it with :class:`cellctl.drivers.plc.ModbusPlc`, the CLI, or any Modbus
client::

    plc = PlcEmulator(time_scale=100.0, on_go=mill1_go)      # on_go(n): GO of CNC n pulsed
    url = await plc.start("modbus://127.0.0.1:0")             # port 0: a free one, reported
    ...
    plc.set_input("part_present_1", True)                     # another emulator drives a sensor
    plc.take_pallet()                                         # the robot lifted the pallet away
    plc.set_fault("stuck-door", "1")                          # door of CNC 1 stops moving
    await plc.close()

What it models (every time **assumed**, :class:`PlcTiming`, divided by ``time_scale``):

- Conveyor: a rising ``pallet_request`` makes the conveyor bring a pallet; ``pallet_present``
  goes 1 after ``conveyor_s`` (none if a pallet is there or on its way). The pallet stays
  until a rising ``pallet_release`` sends it to the outfeed (``pallet_present`` 0 after
  ``release_s``, ``outfeed_clear`` 0 until the outfeed has carried it off ``outfeed_s``
  later) or until :meth:`take_pallet` (the cell emulator calls it when the robot lifts the
  whole pallet). Lowering ``pallet_request`` does not recall a pallet on its way.
- Vises: ``clamp_closed_N`` follows ``clamp_N`` after ``clamp_s``.
- Doors: on a change of ``door_N`` the door leaves its end position at once
  (``door_open_N`` = ``door_closed_N`` = 0) and reaches the other after ``door_s``; the two
  inputs are never 1 together. A door reversed mid-way takes the full time again.
- GO: a rising ``go_N`` is counted in :attr:`go_count` and calls every ``hooks.go`` callback
  with ``N`` (the cell emulator wires it to the mill's GO input). ``part_present_N`` is a
  sensor only: :meth:`set_input` drives it.
- Emergency stop: while ``estop_ok`` is 0 actuators stop where they are and ignore their
  coils, and GO edges are not passed on; once it is 1 again they follow their coils.

``hooks.coil`` callbacks get ``(name, value)`` on every coil change, ``hooks.input`` on every
input change, so the cell emulator can tie robot DO/DI lines to PLC signals.

Fault switches, :data:`FAULTS`: ``drop``, ``silent``, ``stuck-door=N``, ``no-pallet``, ``estop``,
``slow[=MS]``. ``drop`` and ``silent`` act on the TCP line: clients reach pymodbus through a small
front door of our own, so a fault can cut or mute the line as a failed PLC or gateway would.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from cellctl.clock import Clock, current_clock, emulator_clock
from cellctl.emulators.onsets import FaultOnsets
from cellctl.emulators.switches import check_switch
from cellctl.errors import FramingError, UsageError
from cellctl.link import ETHERNET_LINE
from cellctl.link.mem import MemListener, MemPort, listen_mem
from cellctl.protocol import modbus
from cellctl.protocol.plc import (
    COIL,
    INPUT,
    MILLS,
    SIGNALS,
    PlcMap,
    PlcTiming,
    canonical,
    parse_modbus_url,
    plc_mem_name,
)
from cellctl.tasks import cancel_and_wait

__all__ = ["FAULTS", "PlcEmulator", "PlcHooks", "PlcTiming"]

SLOW_DEFAULT_MS = 400  #: how late ``slow`` answers without its ``=MS`` (its description says)
#: Fault switches: name -> what it does (``--fault NAME[=ARG]`` on the command line).
FAULTS: dict[str, str] = {
    "drop": "close every client connection and refuse new ones until cleared",
    "silent": "accept connections and requests but never answer",
    "stuck-door": "=N: the door of CNC N stops where it is and ignores its coil",
    "no-pallet": "the conveyor never delivers a pallet",
    "estop": "emergency stop pressed: estop_ok = 0, actuators stop, GO ignored",
    "slow": "=MS: answer every request MS milliseconds late, in the host's seconds (a busy "
    f"PLC or network) (default {SLOW_DEFAULT_MS} ms)",
}

#: Inputs at power-up: doors closed, vises open, no pallet, outfeed empty, e-stop released.
_INITIAL_INPUTS = {"outfeed_clear": True, "door_closed_1": True, "door_closed_2": True}


@dataclass
class PlcHooks:
    """Callbacks for other emulators: ``coil(name, value)``, ``input(name, value)``, ``go(n)``."""

    coil: list[Callable[[str, bool], None]] = field(default_factory=list)
    input: list[Callable[[str, bool], None]] = field(default_factory=list)
    go: list[Callable[[int], None]] = field(default_factory=list)


class PlcEmulator:
    """A Modbus/TCP PLC with the cell's conveyor, vises and doors behind its IO map."""

    def __init__(
        self,
        plc_map: PlcMap | None = None,
        *,
        time_scale: float | None = None,
        clock: Clock | None = None,
        timing: PlcTiming | None = None,
        on_go: Callable[[int], None] | None = None,
    ) -> None:
        self._clock = emulator_clock(clock, time_scale)
        self.map = plc_map or PlcMap()
        self._closing = False
        self.timing = timing or PlcTiming()
        self.hooks = PlcHooks()
        if on_go is not None:
            self.hooks.go.append(on_go)
        self.coils: dict[str, bool] = {n: False for n in self.map.coils}
        self.inputs: dict[str, bool] = {n: _INITIAL_INPUTS.get(n, False) for n in self.map.inputs}
        self.inputs["estop_ok"] = True
        # Unwired optional sensors still have a state, so the model stays one model.
        for name, sig in SIGNALS.items():
            if sig.kind == INPUT:
                self.inputs.setdefault(name, _INITIAL_INPUTS.get(name, False))
        self.faults: dict[str, str | None] = {}
        self.onsets = FaultOnsets()
        self.go_count: dict[int, int] = {n: 0 for n in MILLS}
        self.pallets_delivered = 0
        self.pallets_released = 0
        self.requests_served = 0
        self._timers: dict[str, asyncio.TimerHandle] = {}
        self._pallet_coming = False
        self._server: Any = None
        self._front: asyncio.Server | None = None
        self._clients: set[asyncio.StreamWriter] = set()
        self._client_tasks: set[asyncio.Task[None]] = set()
        self._backend: tuple[str, int] = ("127.0.0.1", 0)
        self._mem: MemListener | None = None
        self._mem_ports: set[MemPort] = set()
        self.url = ""

    # -- state for tests and other emulators ----------------------------------------------------

    def set_input(self, name: str, value: bool) -> None:
        """Drive discrete input ``name`` (a sensor another emulator or a test controls)."""
        name = canonical(name)
        sig = SIGNALS.get(name)
        if sig is None or sig.kind != INPUT:
            raise UsageError(f"no PLC input {name!r}")
        self._set_input(name, bool(value))

    def set_coil(self, name: str, value: bool) -> None:
        """Set coil ``name`` as a Modbus write would (the model reacts the same way)."""
        name = canonical(name)
        sig = SIGNALS.get(name)
        if sig is None or sig.kind != COIL or name not in self.coils:
            raise UsageError(f"no PLC coil {name!r}")
        self._coil_written(name, bool(value))

    def take_pallet(self) -> None:
        """The pallet at the pick-up was lifted away (by the robot): ``pallet_present`` = 0."""
        self._set_input("pallet_present", False)

    def set_fault(self, name: str, arg: str | None = None) -> None:
        """Switch a fault on (names in :data:`FAULTS`)."""
        check_switch(FAULTS, name, arg)
        if name == "slow" and arg is not None:
            try:
                ms = float(arg)
            except ValueError:
                ms = -1.0
            if not 0.0 <= ms <= 60_000.0:
                raise UsageError(f"slow takes milliseconds from 0 to 60000, not {arg!r}")
        if name == "stuck-door":
            try:
                mill = int(arg) if arg is not None else 0
            except ValueError:
                mill = 0
            if mill not in MILLS:
                given = f", not {arg!r}" if arg is not None else ": stuck-door=1"
                raise UsageError(f"stuck-door needs a mill number 1 or 2{given}")
            # Several stuck doors at once: keep them all, comma separated.
            stuck = self._stuck_doors() | {mill}
            arg = ",".join(str(n) for n in sorted(stuck))
            self._cancel(f"door_{mill}")
        self.faults[name] = arg
        self.onsets.arm(name)
        if name in ("drop", "estop"):
            self.onsets.act(name)
        if name == "drop":
            for writer in list(self._clients):
                writer.transport.abort()
            for port in list(self._mem_ports):
                port.drop()
        elif name == "no-pallet":
            if self._pallet_coming:
                self.onsets.act(name)  # the pallet on its way never comes
            self._cancel("pallet_request")
            self._pallet_coming = False
        elif name == "estop":
            for key in list(self._timers):
                self._cancel(key)
            self._pallet_coming = False
            self._set_input("estop_ok", False)

    async def operator_after(self, fault: str) -> None:
        """Nothing for an operator to do once a PLC fault is off (as for a machine's
        emulator, :meth:`EmulatedDevice.operator_after`): its actuators follow by themselves."""

    def clear_fault(self, name: str) -> None:
        """Switch a fault off (no error if it was off); actuators then follow their coils."""
        self.faults.pop(name, None)
        if name == "estop":
            self._set_input("estop_ok", True)
            if not self.inputs["outfeed_clear"]:
                self._outfeed_moves()
            for n in MILLS:
                self._follow_clamp(n)
                self._follow_door(n)
        elif name == "stuck-door":
            for n in MILLS:
                self._follow_door(n)

    def _stuck_doors(self) -> set[int]:
        arg = self.faults.get("stuck-door")
        return {int(x) for x in arg.split(",")} if arg else set()

    # -- the model ------------------------------------------------------------------------------

    def _set_input(self, name: str, value: bool) -> None:
        if self.inputs.get(name) == value:
            return
        self.inputs[name] = value
        for hook in list(self.hooks.input):
            hook(name, value)

    @property
    def clock(self) -> Clock:
        """What the PLC times its conveyor, vises and doors on: the clock given, else the loop's."""
        return self._clock or current_clock()

    @property
    def time_scale(self) -> float:
        """Seconds of machine time per second of its clock."""
        return self.clock.time_scale

    @time_scale.setter
    def time_scale(self, value: float) -> None:
        self._clock = emulator_clock(None, value)

    def _after(self, key: str, machine_s: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` after ``machine_s`` of machine time, replacing what ``key`` had pending."""
        self._cancel(key)
        clock = self.clock

        def fire() -> None:
            self._timers.pop(key, None)
            fn()

        self._timers[key] = clock.call_at(clock.monotonic() + machine_s / clock.time_scale, fire)

    def _cancel(self, key: str) -> None:
        timer = self._timers.pop(key, None)
        if timer is not None:
            timer.cancel()

    @property
    def _estop(self) -> bool:
        return "estop" in self.faults

    def _coil_written(self, name: str, value: bool) -> None:
        old = self.coils.get(name, False)
        self.coils[name] = value
        if old == value:
            return
        for hook in list(self.hooks.coil):
            hook(name, value)
        rising = value and not old
        if name == "pallet_request" and rising:
            self._request_pallet()
        elif name == "pallet_release" and rising:
            self._release_pallet()
        elif name.startswith("clamp_"):
            self._follow_clamp(int(name[-1]))
        elif name.startswith("door_"):
            self._follow_door(int(name[-1]))
        elif name.startswith("go_") and rising:
            mill = int(name[-1])
            if self._estop:
                return
            self.go_count[mill] += 1
            for go_hook in list(self.hooks.go):
                go_hook(mill)

    def _request_pallet(self) -> None:
        if "no-pallet" in self.faults and not self._estop:
            self.onsets.act("no-pallet")  # a request the conveyor ignores
        busy = self.inputs["pallet_present"] or self._pallet_coming
        if self._estop or "no-pallet" in self.faults or busy:
            return
        self._pallet_coming = True

        def arrive() -> None:
            self._pallet_coming = False
            self.pallets_delivered += 1
            self._set_input("pallet_present", True)

        self._after("pallet_request", self.timing.conveyor_s, arrive)

    def _release_pallet(self) -> None:
        if self._estop or not self.inputs["pallet_present"]:
            return

        def left() -> None:
            self.pallets_released += 1
            self._set_input("pallet_present", False)
            self._set_input("outfeed_clear", False)
            self._outfeed_moves()

        self._after("pallet_release", self.timing.release_s, left)

    def _outfeed_moves(self) -> None:
        self._after(
            "outfeed", self.timing.outfeed_s, lambda: self._set_input("outfeed_clear", True)
        )

    def _follow_clamp(self, mill: int) -> None:
        want = self.coils.get(f"clamp_{mill}", False)
        key = f"clamp_{mill}"
        if self._estop:
            return
        if self.inputs[f"clamp_closed_{mill}"] == want:
            self._cancel(key)
            return
        self._after(key, self.timing.clamp_s, lambda: self._set_input(f"clamp_closed_{mill}", want))

    def _follow_door(self, mill: int) -> None:
        want_open = self.coils.get(f"door_{mill}", False)
        key = f"door_{mill}"
        there = f"door_open_{mill}" if want_open else f"door_closed_{mill}"
        if mill in self._stuck_doors() and not self.inputs[there]:
            self.onsets.act("stuck-door")  # told to move, it does not
        if self._estop or mill in self._stuck_doors():
            return
        if self.inputs[there]:
            self._cancel(key)
            return
        # Leaving an end position: neither switch is made while the door travels.
        self._set_input(f"door_open_{mill}", False)
        self._set_input(f"door_closed_{mill}", False)
        self._after(key, self.timing.door_s, lambda: self._set_input(there, True))

    # -- Modbus ---------------------------------------------------------------------------------

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int] | list[bool] | None,
    ) -> None:
        """pymodbus calls this on every request, before it answers from ``registers``."""
        self.requests_served += 1
        if values is not None and function_code in (5, 15):
            by_address = {a: n for n, a in self.map.coils.items()}
            for i, value in enumerate(values):
                name = by_address.get(address + i)
                if name is not None:
                    self._coil_written(name, bool(value))
        # The model is the truth: refresh the whole block from it before pymodbus reads it
        # (a write is laid over this afterwards and matches the model already).
        if function_code in (1, 5, 15):
            state: Mapping[str, int] = self.map.coils
            levels: Mapping[str, bool] = self.coils
        elif function_code == 2:
            state, levels = self.map.inputs, self.inputs
        else:
            return
        words = [0] * (len(registers) - 1)  # the last register is pymodbus's end marker
        for name, bit_address in state.items():
            if levels.get(name):
                index = bit_address // 16 - start_address
                if 0 <= index < len(words):
                    words[index] |= 1 << (bit_address % 16)
        registers[: len(words)] = words

    def _device(self) -> Any:
        from pymodbus.simulator import DataType, SimData, SimDevice

        def bits(addresses: Mapping[str, int]) -> list[Any]:
            return [SimData(0, count=_block_size(addresses), values=False, datatype=DataType.BITS)]

        regs = [SimData(0, count=1, values=0, datatype=DataType.REGISTERS)]
        # id 0: answer whatever unit id the controller uses, as a PLC on its own port does.
        return SimDevice(
            id=0,
            simdata=(bits(self.map.coils), bits(self.map.inputs), regs, list(regs)),
            action=self._action,
        )

    async def start(self, listen: str = "modbus://127.0.0.1:0") -> str:
        """Listen at ``listen`` (port 0 picks a free one); returns :attr:`url`.

        ``mem://NAME`` serves the same model in the running event loop instead: Modbus/TCP
        frames (:mod:`cellctl.protocol.modbus`) over a ``mem://`` line, no socket (what a
        virtual-time run takes)."""
        from pymodbus.server import ModbusTcpServer

        name = plc_mem_name(listen)
        if name is not None:
            self._mem = listen_mem(name, ETHERNET_LINE, self._mem_client, pacing=False)
            self.url = self._mem.url
            return self.url
        host, port = parse_modbus_url(listen)
        server = ModbusTcpServer(self._device(), address=("127.0.0.1", 0))
        await server.serve_forever(background=True)
        self._server = server
        listener: asyncio.Server = server.transport  # type: ignore[assignment]
        self._backend = ("127.0.0.1", int(listener.sockets[0].getsockname()[1]))
        try:
            self._front = await asyncio.start_server(self._client, host, port)
        except OSError as e:
            await self.close()
            raise UsageError(f"cannot listen on {listen}: {e.strerror or e}") from None
        bound = self._front.sockets[0].getsockname()
        self.url = f"modbus://{bound[0]}:{bound[1]}"
        return self.url

    @property
    def backend_url(self) -> str:
        """pymodbus itself, behind the front door (loopback only). No fault switch acts
        there: it is announced so that nothing listens unsaid, not to be driven."""
        return f"modbus://{self._backend[0]}:{self._backend[1]}"

    async def close(self) -> None:
        """Stop serving: cut every connection, close the listener and pymodbus, stop timers."""
        self._closing = True
        for key in list(self._timers):
            self._cancel(key)
        if self._mem is not None:
            self._mem.close()
            self._mem = None
        for port in list(self._mem_ports):
            port.drop()
        if self._front is not None:
            self._front.close()
        for writer in list(self._clients):
            writer.transport.abort()
        await cancel_and_wait(self._client_tasks)
        if self._front is not None:
            with contextlib.suppress(Exception):
                await self._front.wait_closed()
            self._front = None
        if self._server is not None:
            with contextlib.suppress(Exception):
                await self._server.shutdown()
            self._server = None

    async def __aenter__(self) -> PlcEmulator:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One client: carry bytes to and from pymodbus unless a fault cuts or mutes the line."""
        task = asyncio.current_task()
        assert task is not None
        self._client_tasks.add(task)
        self._clients.add(writer)
        try:
            if "drop" in self.faults:
                writer.transport.abort()
                return
            try:
                up_reader, up_writer = await asyncio.open_connection(*self._backend)
            except OSError:
                writer.transport.abort()
                return
            try:
                await self._carry(reader, writer, up_reader, up_writer)
            finally:
                up_writer.transport.abort()
        except asyncio.CancelledError:
            # close() cancels client tasks; asyncio's stream server would report a cancelled
            # handler as an error, so a cancellation on the way out ends it quietly.
            if not self._closing:
                raise
        finally:
            self._clients.discard(writer)
            self._client_tasks.discard(task)
            writer.transport.abort()

    async def _carry(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        up_reader: asyncio.StreamReader,
        up_writer: asyncio.StreamWriter,
    ) -> None:
        async def down() -> None:
            while data := await up_reader.read(4096):
                if "silent" in self.faults:
                    continue  # a reply to a request sent just before the fault: swallowed
                if late := self._late_s():
                    await self.clock.sleep(late)
                writer.write(data)
                await writer.drain()

        answers = asyncio.ensure_future(down())
        try:
            while data := await reader.read(4096):
                if "silent" in self.faults:
                    self.onsets.act("silent")
                    continue  # read and never answer: the request goes nowhere
                up_writer.write(data)
                await up_writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            answers.cancel()
            with contextlib.suppress(BaseException):
                await answers

    # -- Modbus/TCP in the same event loop (mem://) -------------------------------------------

    def _mem_client(self, port: MemPort) -> None:
        """One host on the mem:// line: answer its frames from the model, as pymodbus does."""
        if "drop" in self.faults:
            port.drop()  # as the TCP front door: the connection is cut at once
            return
        self._mem_ports.add(port)
        reader = modbus.AduReader()

        def on_data(data: bytes) -> None:
            try:
                adus = reader.feed(data)
            except FramingError:
                port.drop()  # no frame boundary left to find: a server closes the connection
                return
            for adu in adus:
                if "silent" in self.faults:
                    self.onsets.act("silent")
                    continue  # read and never answer
                answer = self._answer(adu)
                if late := self._late_s():
                    clock = self.clock
                    clock.call_at(clock.monotonic() + late, answer_late, answer)
                else:
                    port.write(answer)

        def answer_late(answer: bytes) -> None:
            if port in self._mem_ports:  # not after the line closed
                port.write(answer)

        def on_closed() -> None:
            self._mem_ports.discard(port)

        port.on_data = on_data
        port.on_closed = on_closed

    def _late_s(self) -> float:
        """How late each answer goes (the ``slow`` switch), in the clock's seconds."""
        if "slow" not in self.faults:
            return 0.0
        self.onsets.act("slow")
        return float(self.faults["slow"] or SLOW_DEFAULT_MS) / 1000.0  # checked by set_fault

    def _answer(self, adu: modbus.Adu) -> bytes:
        """The answer to one request frame (an exception response for an illegal one)."""
        self.requests_served += 1
        try:
            request = modbus.decode_request(adu)
        except modbus.IllegalRequest as e:
            return modbus.encode_exception(adu.transaction, adu.unit, e.function, e.code)
        tid, unit = adu.transaction, adu.unit
        if request.function == modbus.WRITE_SINGLE_COIL:
            if request.address >= _block_size(self.map.coils):
                return modbus.encode_exception(tid, unit, request.function, _ILLEGAL_ADDRESS)
            name = {a: n for n, a in self.map.coils.items()}.get(request.address)
            if name is not None:
                self._coil_written(name, request.value)
            return modbus.encode_write_coil_response(tid, unit, request.address, request.value)
        if request.function == modbus.READ_COILS:
            addresses, levels = self.map.coils, self.coils
        else:
            addresses, levels = self.map.inputs, self.inputs
        if request.address + request.count > _block_size(addresses):
            return modbus.encode_exception(tid, unit, request.function, _ILLEGAL_ADDRESS)
        by_bit = {a: bool(levels.get(n)) for n, a in addresses.items()}
        bits = [by_bit.get(request.address + i, False) for i in range(request.count)]
        return modbus.encode_bits_response(tid, unit, request.function, bits)


#: Modbus exception 02, illegal data address: a read or write outside the PLC's bit blocks.
_ILLEGAL_ADDRESS = 2


def _block_size(addresses: Mapping[str, int]) -> int:
    """How many bits a block holds (pymodbus's blocks here: whole 16-bit words from 0)."""
    return (max(addresses.values(), default=0) // 16 + 1) * 16
