"""The cell PLC over Modbus/TCP: read its sensors, switch its actuators, wait for a signal.

One :class:`ModbusPlc` per PLC; signal names and addresses come from a
:class:`~cellctl.protocol.plc.PlcMap` (``[plc]`` in ``cell.toml``)::

    plc = await ModbusPlc.connect("modbus://10.0.0.9:502", plc_map, timeout=1.0)
    inputs = await plc.read_inputs()            # {"pallet_present": True, ...}: one request
    await plc.write("door_1", True)             # open the door of CNC 1
    await plc.wait_for("door_open_1", True, timeout=5)
    await plc.pulse("go_1", 0.5)                # start the program loaded in CNC 1
    await plc.close()

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
from cellctl.errors import (
    DeviceError,
    LinkClosed,
    LinkError,
    LinkTimeout,
    SignalTimeout,
    UsageError,
)
from cellctl.protocol.plc import (
    COIL,
    INPUT,
    MODBUS_EXCEPTIONS,
    SIGNALS,
    PlcMap,
    canonical,
    parse_modbus_url,
)

__all__ = ["ModbusPlc"]


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
        host, port = parse_modbus_url(url)
        self._lost = asyncio.Event()
        self._closed = False
        self._address = (host, port)
        self._client: Any = self._new_client()

    @property
    def clock(self) -> Clock:
        """What pulses and waits are timed on: the clock given, else the running loop's."""
        return self._clock or current_clock()

    def _new_client(self) -> Any:
        """A fresh pymodbus client. No retries and no background reconnects: every call has
        one deadline, and the driver reconnects itself on the next call after a failure."""
        from pymodbus.client import AsyncModbusTcpClient

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
    ) -> ModbusPlc:
        """Connect to the PLC at ``url`` (default: the map's) and return a driver.

        ``timeout`` (default: the map's) bounds every request. Raises :class:`LinkError` if
        the PLC cannot be reached.
        """
        plc_map = plc_map or PlcMap()
        plc = cls(url or plc_map.url, plc_map, timeout=timeout or plc_map.timeout, clock=clock)
        try:
            async with plc.clock.timeout(plc.timeout):
                await plc._ensure_connected()
        except TimeoutError:
            plc._client.close()
            raise LinkTimeout(f"PLC at {plc.url}: no connection within {plc.timeout:g} s") from None
        return plc

    async def close(self) -> None:
        """Close the connection (calls after this raise :class:`LinkClosed`)."""
        self._closed = True
        self._client.close()

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
        self, name: str, value: bool, *, timeout: float, poll: float | None = None
    ) -> dict[str, bool]:
        """Read the inputs every ``poll`` s until input ``name`` is ``value``; return them.

        Raises :class:`SignalTimeout` in words once ``timeout`` passes ("door of CNC 1 did not
        close within 5 s"); a read under way at the deadline is finished first, so the wait
        ends at most one request timeout late. Link failures while reading pass through.
        """
        name = self._signal(name, INPUT)
        poll = self.map.poll if poll is None else poll
        if timeout < 0 or poll <= 0:
            raise UsageError("wait_for needs timeout >= 0 and poll > 0")
        clock = self.clock
        deadline = clock.monotonic() + timeout
        want = bool(value)
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
