"""The cell PLC over Modbus/TCP: read its sensors, switch its actuators, wait for a signal.

One :class:`ModbusPlc` per PLC; signal names and addresses come from a
:class:`~cellctl.protocol.plc.PlcMap` (``[plc]`` in ``cell.toml``)::

    plc = await ModbusPlc.connect("modbus://10.0.0.9:502", plc_map, timeout=1.0)
    inputs = await plc.read_inputs()            # {"pallet_present": True, ...}: one request
    await plc.write("door_1", True)             # open the door of CNC 1
    await plc.wait_for("door_open_1", True, timeout=5)
    await plc.pulse("go_1", 0.5)                # start the program loaded in CNC 1
    await plc.close()

``mem://NAME`` instead of ``modbus://`` reaches a PLC emulator in the same event loop
(``PlcEmulator.start("mem://NAME")``): the same Modbus/TCP frames
(:mod:`cellctl.protocol.modbus`) over a ``mem://`` line, what a run on virtual time uses;
over TCP, pymodbus does the framing.

Requests used (Modbus application protocol): 02 Read Discrete Inputs (all mapped inputs in
one request, from the lowest to the highest address), 01 Read Coils, 05 Write Single Coil.

Every call has a deadline (``timeout``, for connecting and answering together). Failures are
typed: no connection or a connection closed under us -> :class:`LinkError`
(:class:`LinkClosed`), no answer in time -> :class:`LinkTimeout` (the connection is then
closed so a late answer cannot be taken for the next one; the next call reconnects), a Modbus
exception response -> :class:`DeviceError` with the exception code and its name, an unknown
or unwired signal name or a write to an input -> :class:`UsageError` before anything is sent.
A wait for an input that runs out says what did not happen: "door of CNC 1 did not close
within 5 s".
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

from cellctl.clock import Clock, current_clock
from cellctl.drivers.base import release_locks, take_link_locks
from cellctl.drivers.state import StateStore
from cellctl.errors import (
    DeviceError,
    LinkClosed,
    LinkError,
    LinkTimeout,
    ProtocolError,
    SignalTimeout,
    UsageError,
)
from cellctl.link import ETHERNET_LINE, Link, open_link
from cellctl.link.lock import OwnerLock
from cellctl.protocol import modbus
from cellctl.protocol.plc import (
    COIL,
    INPUT,
    MODBUS_EXCEPTIONS,
    SIGNALS,
    PlcMap,
    canonical,
    parse_modbus_url,
    plc_mem_name,
)

__all__ = ["MemModbusClient", "ModbusPlc"]


def _retrieve(future: asyncio.Future[Any]) -> None:
    """Take a finished request's outcome (its failure, if any, was raised as a typed error)."""
    if not future.cancelled():
        future.exception()


class ModbusPlc:
    """Driver for the cell's PLC; build it with :meth:`connect`."""

    def __init__(
        self, url: str, plc_map: PlcMap, *, timeout: float, clock: Clock | None = None
    ) -> None:
        if timeout <= 0:
            raise UsageError(f"timeout must be > 0 s, not {timeout}")
        self.url = url
        self.map = plc_map
        self.timeout = timeout
        self._clock = clock
        self.requests = 0
        self.last_inputs: dict[str, bool] = {}
        self._maybe_high: set[str] = set()  # coils a failed pulse may have left at 1
        self._mem = plc_mem_name(url) is not None
        host, port = ("", 0) if self._mem else parse_modbus_url(url)
        self._lost = asyncio.Event()
        self._closed = False
        self._address = (host, port)
        self._client: Any = self._new_client()
        self._owner_locks: list[OwnerLock] = []  # taken by connect(), given back by close()

    @property
    def clock(self) -> Clock:
        """What pulses and waits are timed on: the clock given, else the running loop's."""
        return self._clock or current_clock()

    def _new_client(self) -> Any:
        """A fresh client: pymodbus's over TCP, :class:`MemModbusClient` over ``mem://``. No
        retries and no background reconnects: every call has one deadline, and the driver
        reconnects itself on the next call after a failure."""
        from pymodbus.client import AsyncModbusTcpClient

        if self._mem:
            # The line is free once the last client's close is through: it waits for that.
            previous = getattr(self, "_client", None)
            return MemModbusClient(self.url, self.timeout, previous=previous)
        host, port = self._address
        client: Any = None

        def changed(connected: bool) -> None:
            if client is self._client:  # a replaced client's late news is not ours
                self._connection_changed(connected)

        client = AsyncModbusTcpClient(
            host,
            port=port,
            timeout=self.timeout,
            retries=0,
            reconnect_delay=0,
            trace_connect=changed,
        )
        return client

    def _drop_client(self) -> None:
        """Close the connection after a failure and start the next call on a new client.

        pymodbus keeps state across a reconnect (after three unanswered requests it gives up
        on a connection by itself and could go on sending into the closed one): a failed
        connection's client is never used again.
        """
        self._client.close()
        self._client = self._new_client()

    @classmethod
    async def connect(
        cls,
        url: str | None = None,
        plc_map: PlcMap | None = None,
        *,
        timeout: float | None = None,
        clock: Clock | None = None,
        store: StateStore | None = None,
        name: str = "plc",
    ) -> ModbusPlc:
        """Connect to the PLC at ``url`` (default: the map's) and return a driver.

        ``timeout`` (default: the map's) bounds every request. Raises :class:`LinkError` if
        the PLC cannot be reached. One owner, as for a machine: the PLC's locks are taken
        first, by URL and, with the cell's ``store``, by ``name`` in the cell
        (:class:`MachineInUse` names the holder, before a request goes out).
        """
        plc_map = plc_map or PlcMap()
        plc = cls(url or plc_map.url, plc_map, timeout=timeout or plc_map.timeout, clock=clock)
        plc._owner_locks = await take_link_locks(plc.url, name, store)
        try:
            async with plc.clock.timeout(plc.timeout):
                await plc._ensure_connected()
        except TimeoutError:
            plc._client.close()
            release_locks(plc._owner_locks)
            raise LinkTimeout(f"PLC at {plc.url}: no connection within {plc.timeout:g} s") from None
        except BaseException:
            plc._client.close()
            release_locks(plc._owner_locks)
            raise
        return plc

    async def close(self) -> None:
        """Close the connection (calls after this raise :class:`LinkClosed`) and give back
        the PLC's locks."""
        self._closed = True
        self._client.close()
        try:
            if isinstance(self._client, MemModbusClient):
                await self._client.wait_closed()
        finally:
            release_locks(self._owner_locks)
            self._owner_locks = []

    async def __aenter__(self) -> ModbusPlc:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- the connection -------------------------------------------------------------------------

    def _connection_changed(self, connected: bool) -> None:
        if connected:
            self._lost.clear()
        else:
            self._lost.set()

    async def _ensure_connected(self) -> None:
        if self._closed:
            raise LinkClosed(f"PLC at {self.url}: the connection was closed")
        if self._client.connected:
            return
        if not await self._client.connect():
            raise LinkError(
                f"cannot reach the PLC at {self.url}: connection refused, or no PLC there"
            )
        self._lost.clear()

    async def _request(self, what: str, call: Callable[[], Awaitable[Any]]) -> Any:
        """Send one request with a deadline; map every failure to a typed error."""
        from pymodbus.exceptions import ConnectionException, ModbusException

        answer: asyncio.Future[Any] | None = None
        try:
            async with self.clock.timeout(self.timeout):
                await self._ensure_connected()
                self.requests += 1
                if isinstance(self._client, MemModbusClient):
                    # A mem:// line raises LinkClosed itself when the far end goes: no watch.
                    return self._checked(what, await call())
                answer = asyncio.ensure_future(call())
                lost = asyncio.ensure_future(self._lost.wait())
                try:
                    await asyncio.wait({answer, lost}, return_when=asyncio.FIRST_COMPLETED)
                finally:
                    lost.cancel()
                if not answer.done():
                    raise LinkClosed(f"PLC at {self.url} closed the connection ({what})")
                response = answer.result()
        except TimeoutError:
            self._drop_client()  # a late answer must not pass for the next request's
            raise LinkTimeout(
                f"PLC at {self.url}: no answer to {what} within {self.timeout:g} s"
            ) from None
        except ConnectionException:
            self._drop_client()
            raise LinkClosed(f"PLC at {self.url}: connection lost ({what})") from None
        except LinkTimeout:
            self._drop_client()
            raise LinkTimeout(
                f"PLC at {self.url}: no answer to {what} within {self.timeout:g} s"
            ) from None
        except LinkError:
            self._drop_client()
            raise LinkClosed(f"PLC at {self.url} closed the connection ({what})") from None
        except ProtocolError:
            self._drop_client()  # the stream is out of step: never read it again
            raise
        except ModbusException as e:
            was_lost = self._lost.is_set()
            self._drop_client()
            if was_lost:
                raise LinkClosed(f"PLC at {self.url} closed the connection ({what})") from None
            raise LinkTimeout(f"PLC at {self.url}: no valid answer to {what}: {e}") from None
        finally:
            # A request left behind (the deadline ran out, the connection was lost) is ended
            # here, and its outcome taken: the error raised above already tells it.
            if answer is not None and not answer.done():
                answer.cancel()
            if answer is not None:
                answer.add_done_callback(_retrieve)
        return self._checked(what, response)

    def _checked(self, what: str, response: Any) -> Any:
        """``response``, or :class:`DeviceError` for a Modbus exception response."""
        if response.isError():
            code = int(getattr(response, "exception_code", 0))
            name = MODBUS_EXCEPTIONS.get(code, "unknown Modbus exception")
            raise DeviceError(code, name, detail=f"PLC at {self.url} refused {what}")
        return response

    # -- signals --------------------------------------------------------------------------------

    def _signal(self, name: str, kind: str | None = None) -> str:
        """Canonical name of a mapped signal; :class:`UsageError` if unknown or the wrong kind."""
        name = canonical(name)
        actual = self.map.kind_of(name)
        if kind == COIL and actual != COIL:
            raise UsageError(f"{name} is an input the PLC reads; only coils can be written")
        if kind == INPUT and actual != INPUT:
            raise UsageError(f"{name} is a coil the controller writes; wait for an input")
        return name

    async def read_inputs(self) -> dict[str, bool]:
        """Every mapped discrete input, by name, read in one request."""
        first, count = self.map.input_block
        if not count:
            return {}
        response = await self._request(
            f"reading inputs {first}..{first + count - 1}",
            lambda: self._client.read_discrete_inputs(first, count=count, device_id=self.map.unit),
        )
        bits = list(response.bits)
        self.last_inputs = {
            name: bool(bits[address - first]) for name, address in self.map.inputs.items()
        }
        return dict(self.last_inputs)

    async def read_coils(self) -> dict[str, bool]:
        """Every mapped coil, by name, as the PLC holds it (one request)."""
        first, count = self.map.coil_block
        if not count:
            return {}
        response = await self._request(
            f"reading coils {first}..{first + count - 1}",
            lambda: self._client.read_coils(first, count=count, device_id=self.map.unit),
        )
        bits = list(response.bits)
        return {name: bool(bits[address - first]) for name, address in self.map.coils.items()}

    async def read(self, name: str) -> bool:
        """One signal's level: an input (from a read of all inputs) or a coil."""
        name = self._signal(name)
        if self.map.kind_of(name) == INPUT:
            return (await self.read_inputs())[name]
        return (await self.read_coils())[name]

    async def write(self, name: str, value: bool) -> None:
        """Set coil ``name`` to ``value`` (e.g. ``write("clamp_2", True)`` clamps CNC 2's vise)."""
        name = self._signal(name, COIL)
        address = self.map.coils[name]
        await self._request(
            f"setting {name} (coil {address}) to {int(bool(value))}",
            lambda: self._client.write_coil(address, bool(value), device_id=self.map.unit),
        )
        if not value:
            self._maybe_high.discard(name)

    async def pulse(self, name: str, seconds: float = 0.5) -> None:
        """Set coil ``name`` to 1 for ``seconds``, then back to 0 (GO of a mill, a release).

        The coil is lowered even if the caller is cancelled during the pulse. A pulse whose
        lowering failed (the PLC stopped answering) may have left the coil high: the next
        pulse of that coil lowers it first, so the PLC sees a rising edge again.
        """
        if seconds <= 0:
            raise UsageError(f"pulse length must be > 0 s, not {seconds}")
        name = self._signal(name, COIL)
        if name in self._maybe_high:
            await self.write(name, False)
        # Marked before the write: a write that timed out may still have reached the PLC.
        self._maybe_high.add(name)
        await self.write(name, True)
        try:
            await self.clock.sleep(seconds)  # the pulse width itself, not a wait for an event
        finally:
            await asyncio.shield(self.write(name, False))

    async def wait_for(
        self,
        name: str,
        value: bool,
        *,
        timeout: float,
        poll: float | None = None,
        expected: float = 0.0,
    ) -> dict[str, bool]:
        """Read the inputs every ``poll`` s until input ``name`` is ``value``; return them.

        ``expected``: seconds the input cannot get there sooner (a door's least travel time
        seen, say): the first read waits that long (at most ``timeout``), and no read is spent
        on a door still on its way.

        Raises :class:`SignalTimeout` in words once ``timeout`` passes ("door of CNC 1 did not
        close within 5 s"); a read under way at the deadline is finished first, so the wait
        ends at most one request timeout late. Link failures while reading pass through.
        """
        name = self._signal(name, INPUT)
        poll = self.map.poll if poll is None else poll
        if timeout < 0 or poll <= 0 or expected < 0:
            raise UsageError("wait_for needs timeout >= 0, poll > 0 and expected >= 0")
        clock = self.clock
        deadline = clock.monotonic() + timeout
        want = bool(value)
        if expected > 0:
            await clock.sleep(min(expected, timeout))
        while True:
            inputs = await self.read_inputs()
            if inputs[name] == want:
                return inputs
            left = deadline - clock.monotonic()
            if left <= 0:
                sig = SIGNALS[name]
                phrase = sig.not_true if want else sig.not_false
                raise SignalTimeout(f"{phrase} within {timeout:g} s")
            await clock.sleep(min(poll, left))  # the poll period between reads


class MemModbusClient:
    """A Modbus/TCP client over a ``mem://`` line, with the few calls of pymodbus's client
    that :class:`ModbusPlc` uses (``connect``, ``connected``, ``close`` and the three
    requests). One request at a time, in order: answers come back as they were asked.

    Failures are the link's (:class:`LinkClosed`, :class:`LinkTimeout`) and the codec's
    (:class:`~cellctl.errors.ProtocolError`, raw bytes attached).
    """

    def __init__(
        self, url: str, timeout: float, *, previous: MemModbusClient | None = None
    ) -> None:
        self.url = url
        self.timeout = timeout
        self._previous = previous
        self._link: Link | None = None
        self._reader = modbus.AduReader()
        self._transaction = 0
        self._lock = asyncio.Lock()
        self._closing: asyncio.Task[None] | None = None
        self._given_up = False  # closed (replaced) before or while it connected

    @property
    def connected(self) -> bool:
        return self._link is not None and not self._link.closed

    async def connect(self) -> bool:
        """Open the line; False if nothing listens at the URL."""
        if self._previous is not None:
            await self._previous.wait_closed()  # one host at a time on a mem:// line
            self._previous = None
        if self._given_up:
            # Replaced while it waited (another request's failure closed it): a line opened
            # now would be held by a client nobody uses, and the next one refused for ever.
            return False
        try:
            self._link = await open_link(self.url, ETHERNET_LINE, label="plc")
        except LinkError:
            return False
        return True

    def close(self) -> None:
        """Close the line (at once: a mem:// close needs no wait)."""
        self._given_up = True
        link, self._link = self._link, None
        if link is not None and not link.closed:
            self._closing = asyncio.ensure_future(link.close())

    async def wait_closed(self) -> None:
        """Until the line is closed (after :meth:`close`)."""
        if self._closing is not None:
            await self._closing

    async def _call(self, request: modbus.Request, frame: bytes) -> modbus.Response:
        async with self._lock:
            link = self._link
            if link is None or link.closed:
                raise LinkClosed(f"{self.url}: not connected")
            await link.write(frame)
            while True:
                data = await link.read(timeout=self.timeout)
                for adu in self._reader.feed(data):
                    return modbus.decode_response(adu, request)

    def _next(self) -> int:
        self._transaction = (self._transaction + 1) & 0xFFFF
        return self._transaction

    async def _read(self, function: int, address: int, count: int, unit: int) -> Any:
        tid = self._next()
        request = modbus.Request(tid, unit, function, address, count)
        return await self._call(request, modbus.encode_read(tid, unit, function, address, count))

    async def read_discrete_inputs(self, address: int, *, count: int, device_id: int) -> Any:
        return await self._read(modbus.READ_DISCRETE_INPUTS, address, count, device_id)

    async def read_coils(self, address: int, *, count: int, device_id: int) -> Any:
        return await self._read(modbus.READ_COILS, address, count, device_id)

    async def write_coil(self, address: int, value: bool, *, device_id: int) -> Any:
        tid = self._next()
        request = modbus.Request(tid, device_id, modbus.WRITE_SINGLE_COIL, address, 1, value)
        frame = modbus.encode_write_coil(tid, device_id, address, value)
        return await self._call(request, frame)
