"""The in-process Modbus pair: the PLC driver and emulator over ``mem://`` on virtual time give
the same answers as over real Modbus/TCP on loopback (pymodbus on both ends there); the
codec's frames are what pymodbus's server takes; the codec takes any bytes a peer can send.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cellctl.clock import current_clock, run_virtual
from cellctl.drivers.plc import MemModbusClient, ModbusPlc
from cellctl.emulators.plc import PlcEmulator
from cellctl.errors import (
    CellctlError,
    DeviceError,
    FramingError,
    ProtocolError,
    SignalTimeout,
    UsageError,
)
from cellctl.protocol import modbus
from cellctl.protocol.plc import DEFAULT_COILS, DEFAULT_INPUTS, PlcMap, PlcTiming, check_plc_url

WAIT = 30.0  # machine seconds: generous, for events that do happen


async def _session(url: str, emulator: PlcEmulator) -> list[Any]:
    """One session of driver calls; each call's answer, or its error's type (and code)."""
    out: list[Any] = []

    async def note(call: Callable[[], Awaitable[Any]]) -> None:
        try:
            out.append(await call())
        except DeviceError as e:
            out.append(("DeviceError", e.code))
        except CellctlError as e:
            out.append(type(e).__name__)

    scale = emulator.time_scale

    async def level(name: str, value: bool, timeout: float = WAIT) -> bool:
        # The level waited for, not the whole snapshot: the rest moves on machine time.
        return (await plc.wait_for(name, value, timeout=timeout / scale))[name]

    async with await ModbusPlc.connect(url, emulator.map, timeout=3.0) as plc:
        await note(plc.read_inputs)
        await note(plc.read_coils)
        for name in DEFAULT_COILS:
            if name.startswith("go_") or name == "pallet_request":
                continue  # GO and the conveyor act on their own: below
            await note(lambda n=name: plc.write(n, True))  # type: ignore[misc]
        await note(plc.read_coils)
        for name in ("clamp_closed_1", "clamp_closed_2", "door_open_1", "door_open_2"):
            await note(lambda n=name: level(n, True))  # type: ignore[misc]
        await note(lambda: plc.pulse("pallet_request", 1.0 / scale))
        await note(lambda: level("pallet_present", True))
        await note(lambda: plc.pulse("go_1", 0.5 / scale))
        out.append(dict(emulator.go_count))
        emulator.set_input("part_present_2", True)
        await note(plc.read_inputs)
        emulator.set_fault("stuck-door", "1")
        await note(lambda: plc.write("door_1", False))
        await note(lambda: level("door_closed_1", True, timeout=5.0))
        emulator.clear_fault("stuck-door")
        emulator.set_fault("silent")
        await note(plc.read_inputs)
        emulator.clear_fault("silent")
        await note(plc.read_inputs)
        emulator.set_fault("drop")
        await note(plc.read_inputs)
        await note(plc.read_inputs)  # reconnecting is refused too
        emulator.clear_fault("drop")
        await note(plc.read_coils)
    # A map that places an input beyond the PLC's: a Modbus exception, as a DeviceError.
    table = {"inputs": {**DEFAULT_INPUTS, "part_present_2": 300}, "coils": dict(DEFAULT_COILS)}
    wrong = PlcMap.from_toml(table)
    async with await ModbusPlc.connect(url, wrong, timeout=3.0) as plc:
        await note(plc.read_inputs)
        await note(lambda: plc.write("go_2", True))
    return out


def test_the_driver_gets_the_same_answers_over_mem_on_virtual_time_as_over_tcp() -> None:
    async def over(listen: str, time_scale: float) -> tuple[list[Any], float]:
        emulator = PlcEmulator(time_scale=time_scale)
        url = await emulator.start(listen)
        clock = current_clock()
        started = clock.monotonic()
        try:
            answers = await _session(url, emulator)
        finally:
            await emulator.close()
        return answers, clock.monotonic() - started

    tcp, _ = asyncio.run(over("modbus://127.0.0.1:0", 200.0))
    mem, machine_s = run_virtual(over("mem://plc", 1.0))
    assert mem == tcp
    # What the session saw happen (not only that both agree): the model's answers.
    assert tcp[0]["estop_ok"] is True and tcp[0]["pallet_present"] is False
    assert "LinkTimeout" in tcp and "LinkClosed" in tcp and ("DeviceError", 2) in tcp
    assert {1: 1, 2: 0} in tcp
    # On virtual time the machine's own times pass: the conveyor's 8 s at least.
    assert machine_s >= 8.0


def test_the_codec_s_frames_are_what_pymodbus_serves() -> None:
    """The mem:// client's frames, sent over real TCP to pymodbus's server (behind the PLC
    emulator), get the answers the model holds: the codec speaks pymodbus's Modbus/TCP."""

    async def session() -> None:
        emulator = PlcEmulator()
        await emulator.start("modbus://127.0.0.1:0")
        host, port = emulator.backend_url.removeprefix("modbus://").split(":")
        client = MemModbusClient(f"socket://{host}:{port}", timeout=3.0)
        try:
            assert await client.connect()
            first, count = emulator.map.input_block
            reply = await client.read_discrete_inputs(first, count=count, device_id=1)
            expected = [emulator.inputs[n] for n in sorted(DEFAULT_INPUTS, key=DEFAULT_INPUTS.get)]  # type: ignore[arg-type]
            assert list(reply.bits) == expected
            await client.write_coil(DEFAULT_COILS["clamp_2"], True, device_id=1)
            assert emulator.coils["clamp_2"] is True
            reply = await client.read_coils(0, count=len(DEFAULT_COILS), device_id=1)
            assert reply.bits[DEFAULT_COILS["clamp_2"]] is True
            assert sum(reply.bits) == 1
            reply = await client.read_discrete_inputs(300, count=1, device_id=1)
            assert reply.isError() and reply.exception_code == 2
        finally:
            client.close()
            await emulator.close()

    asyncio.run(session())


def test_a_plc_url_is_modbus_or_mem() -> None:
    check_plc_url("mem://plc")
    check_plc_url("modbus://10.0.0.9:502")
    assert PlcMap.from_toml({"url": "mem://cell-plc"}).url == "mem://cell-plc"
    with pytest.raises(UsageError, match="mem:// name"):
        check_plc_url("mem://no/slash")
    with pytest.raises(UsageError, match="modbus://HOST"):
        check_plc_url("http://10.0.0.9")


# -- the codec ---------------------------------------------------------------------------------

transactions = st.integers(0, 0xFFFF)
units = st.integers(0, 0xFF)
addresses = st.integers(0, 0xFFFF)


@given(transactions, units, st.sampled_from([1, 2]), addresses, st.integers(1, 2000), st.data())
def test_a_read_and_its_answer_round_trip(
    tid: int, unit: int, function: int, address: int, count: int, data: st.DataObject
) -> None:
    count = min(count, 0x10000 - address)
    frame = modbus.encode_read(tid, unit, function, address, count)
    (adu,) = modbus.AduReader().feed(frame)
    request = modbus.decode_request(adu)
    assert (request.transaction, request.unit, request.function) == (tid, unit, function)
    assert (request.address, request.count) == (address, count)
    bits = data.draw(st.lists(st.booleans(), min_size=count, max_size=count))
    answer = modbus.encode_bits_response(tid, unit, function, bits)
    (reply,) = modbus.AduReader().feed(answer)
    assert modbus.decode_response(reply, request).bits == tuple(bits)


@given(transactions, units, addresses, st.booleans(), st.integers(1, 8))
def test_a_coil_write_round_trips_in_any_chunks(
    tid: int, unit: int, address: int, value: bool, pieces: int
) -> None:
    frame = modbus.encode_write_coil(tid, unit, address, value) * 2
    reader = modbus.AduReader()
    got: list[modbus.Adu] = []
    step = max(1, len(frame) // pieces)
    for i in range(0, len(frame), step):
        got += reader.feed(frame[i : i + step])
    assert len(got) == 2 and reader.pending == b""
    request = modbus.decode_request(got[0])
    assert (request.address, request.value) == (address, value)
    echo = modbus.encode_write_coil_response(tid, unit, address, value)
    (adu,) = modbus.AduReader().feed(echo)
    assert modbus.decode_response(adu, request).value is value


@given(st.binary(max_size=300))
def test_any_bytes_from_a_peer_give_frames_or_a_protocol_error(data: bytes) -> None:
    reader = modbus.AduReader()
    try:
        adus = reader.feed(data)
    except FramingError as e:
        assert e.raw  # the header that broke it travels with the error
        return
    request = modbus.Request(1, 1, modbus.READ_COILS, 0, 16)
    for adu in adus:
        try:
            modbus.decode_request(adu)
        except modbus.IllegalRequest as e:
            assert e.code in (1, 2, 3)
        try:
            response = modbus.decode_response(adu, request)
        except ProtocolError as e:
            assert e.raw  # what broke travels with the error
        else:
            assert len(response.bits) == 16 or response.isError()


def test_exceptions_and_refusals() -> None:
    frame = modbus.encode_exception(9, 1, modbus.READ_DISCRETE_INPUTS, 2)
    (adu,) = modbus.AduReader().feed(frame)
    request = modbus.Request(9, 1, modbus.READ_DISCRETE_INPUTS, 0, 4)
    response = modbus.decode_response(adu, request)
    assert response.isError() and response.exception_code == 2 and response.bits == ()
    with pytest.raises(modbus.IllegalRequest, match="function 3 is not served") as info:
        modbus.decode_request(modbus.Adu(1, 1, bytes([3, 0, 0, 0, 1])))
    assert info.value.code == 1
    with pytest.raises(modbus.IllegalRequest, match="count 2001") as info:
        modbus.decode_request(modbus.Adu(1, 1, bytes([2, 0, 0, 0x07, 0xD1])))
    assert info.value.code == 3
    with pytest.raises(FramingError, match="protocol id 1") as framing:
        modbus.AduReader().feed(bytes([0, 1, 0, 1, 0, 6, 1]))
    assert framing.value.raw == bytes([0, 1, 0, 1, 0, 6, 1])
    with pytest.raises(ProtocolError, match="transaction 2, expected 9"):
        modbus.decode_response(modbus.Adu(2, 1, bytes([2, 1, 0])), request)


def test_a_wait_told_the_least_travel_time_reads_once_the_door_can_be_there() -> None:
    """A door takes its ``door_s`` to close: read every 5 ms all the way, that is hundreds of
    requests; told how long it cannot take less, the wait reads only near its end. Either
    wait finds the door closed; the expected time never outlasts the wait's deadline."""

    async def close_door(expected: float) -> tuple[int, bool]:
        emulator = PlcEmulator()
        url = await emulator.start("mem://plc-door")
        try:
            async with await ModbusPlc.connect(url, emulator.map, timeout=3.0) as plc:
                await plc.write("door_1", True)
                await plc.wait_for("door_open_1", True, timeout=WAIT, poll=0.005)
                await plc.write("door_1", False)
                await plc.wait_for("door_open_1", False, timeout=WAIT, poll=0.005)
                before = emulator.requests_served
                inputs = await plc.wait_for(
                    "door_closed_1", True, timeout=WAIT, poll=0.005, expected=expected
                )
                return emulator.requests_served - before, inputs["door_closed_1"]
        finally:
            await emulator.close()

    door_s = PlcTiming().door_s
    polled, closed = run_virtual(close_door(0.0))
    told, closed_too = run_virtual(close_door(0.9 * door_s))
    assert closed and closed_too
    assert polled > 100  # every 5 ms for most of door_s
    assert told * 5 < polled  # only the last tenth of the travel is read

    async def stuck() -> float:
        emulator = PlcEmulator()
        url = await emulator.start("mem://plc-stuck")
        emulator.set_fault("stuck-door", "1")
        clock = current_clock()
        try:
            async with await ModbusPlc.connect(url, emulator.map, timeout=3.0) as plc:
                await plc.write("door_1", True)
                started = clock.monotonic()
                with pytest.raises(SignalTimeout, match="within 1 s"):
                    await plc.wait_for("door_open_1", True, timeout=1.0, expected=60.0)
                return clock.monotonic() - started
        finally:
            await emulator.close()

    # The deadline stands: a door that never comes is told at the wait's timeout.
    assert run_virtual(stuck()) < 2.0

    async def refused() -> None:
        emulator = PlcEmulator()
        url = await emulator.start("mem://plc-refused")
        try:
            async with await ModbusPlc.connect(url, emulator.map, timeout=3.0) as plc:
                with pytest.raises(UsageError, match="expected >= 0"):
                    await plc.wait_for("door_open_1", True, timeout=1.0, expected=-1.0)
        finally:
            await emulator.close()

    run_virtual(refused())
