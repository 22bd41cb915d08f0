"""mem:// links: byte-faithful, paced at the line's rate, modem lines carried, one host."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.clock import current_clock, run_virtual
from cellctl.errors import LinkClosed, LinkError, LinkTimeout, MachineInUse, UsageError
from cellctl.link import LineSettings, TrafficLog, open_link
from cellctl.link.mem import PACE_SLICE_S, MemLink, MemPort, listen_mem, listening, mem_name

LINE = LineSettings(4800, 7, "E", 2)  # 11 bits a character: 436 characters a second


@dataclass
class Device:
    """The device end as a test sees it: what arrived, and when (loop time)."""

    port: MemPort | None = None
    received: bytearray = field(default_factory=bytearray)
    arrivals: list[tuple[float, int]] = field(default_factory=list)  # (time, bytes so far)
    closed_at: float | None = None

    def attach(self, port: MemPort) -> None:
        self.port = port
        clock = current_clock()

        def on_data(data: bytes) -> None:
            self.received += data
            self.arrivals.append((clock.monotonic(), len(self.received)))

        def on_closed() -> None:
            self.closed_at = clock.monotonic()

        port.on_data = on_data
        port.on_closed = on_closed


async def _pair(
    settings: LineSettings = LINE, name: str = "m1", **kw: object
) -> tuple[MemLink, Device]:
    device = Device()
    listen_mem(name, settings, device.attach, **kw)  # type: ignore[arg-type]
    link = await open_link(f"mem://{name}", settings)
    assert isinstance(link, MemLink)
    return link, device


async def _read_all(link: MemLink, n: int, timeout: float) -> bytes:
    return await link.read_exactly(n, timeout=timeout) if n else b""


settings_strategy = st.builds(
    LineSettings,
    baudrate=st.sampled_from([300, 1200, 2400, 4800, 9600, 115200]),
    bytesize=st.sampled_from([5, 6, 7, 8]),
    parity=st.sampled_from(list("NEOMS")),
    stopbits=st.sampled_from([1, 1.5, 2]),
)
chunks = st.lists(st.binary(min_size=1, max_size=300), max_size=8)


@settings(max_examples=60, deadline=None)
@given(line=settings_strategy, to_device=chunks, to_host=chunks)
def test_every_byte_arrives_in_order_never_faster_than_the_line(
    line: LineSettings, to_device: list[bytes], to_host: list[bytes]
) -> None:
    """Both ways at once: the far end gets exactly the bytes sent, in order; no byte is there
    before its character could have crossed; the last is there when the line says."""
    sent_down, sent_up = b"".join(to_device), b"".join(to_host)

    async def main() -> None:
        clock = current_clock()
        link, device = await _pair(line)
        assert device.port is not None
        start = clock.monotonic()
        for piece in to_device:
            await link.write(piece)
        for piece in to_host:
            device.port.write(piece)
        got = await _read_all(link, len(sent_up), timeout=len(sent_up) * line.char_time + 1)
        await asyncio.sleep(len(sent_down) * line.char_time + 2 * PACE_SLICE_S)
        assert got == sent_up
        assert bytes(device.received) == sent_down
        for at, so_far in device.arrivals:
            assert at - start >= so_far * line.char_time - 1e-6
        if sent_down:
            last_at, total = device.arrivals[-1]
            assert last_at - start == pytest.approx(total * line.char_time, abs=1e-6)
        if sent_up:
            assert clock.monotonic() >= start + len(sent_up) * line.char_time
        await link.close()

    run_virtual(main())


@settings(max_examples=60, deadline=None)
@given(
    line=settings_strategy,
    writes=st.lists(
        st.tuples(st.floats(min_value=0, max_value=2), st.binary(min_size=1, max_size=40)),
        min_size=1,
        max_size=10,
    ),
)
def test_each_write_ends_when_a_real_line_would_have_carried_it(
    line: LineSettings, writes: list[tuple[float, bytes]]
) -> None:
    """Writes at random moments: each one's last byte arrives when the line, busy with what
    came before, would have carried it (a line idle meanwhile gives no credit)."""

    async def main() -> None:
        clock = current_clock()
        link, device = await _pair(line)
        expected: list[tuple[float, int]] = []  # (last byte through at, bytes so far)
        busy_until, total = clock.monotonic(), 0
        for gap, data in writes:
            await asyncio.sleep(gap)
            await link.write(data)
            busy_until = max(clock.monotonic(), busy_until) + len(data) * line.char_time
            total += len(data)
            expected.append((busy_until, total))
        await asyncio.sleep(busy_until - clock.monotonic() + PACE_SLICE_S)
        assert bytes(device.received) == b"".join(data for _, data in writes)
        # A write's last byte ends a slice, handed over on its own on the virtual loop.
        arrived = {so_far: at for at, so_far in device.arrivals}
        for through, so_far in expected:
            assert arrived[so_far] == pytest.approx(through, abs=1e-6)
        await link.close()

    run_virtual(main())


def test_a_write_after_a_silence_takes_its_own_line_time() -> None:
    async def main() -> None:
        clock = current_clock()
        link, device = await _pair()
        await link.write(b"R")
        await asyncio.sleep(10)  # the line idles: no credit for the next write
        start = clock.monotonic()
        await link.write(b"0123456789")
        await asyncio.sleep(1)
        assert bytes(device.received) == b"R0123456789"
        assert device.arrivals[-1][0] - start == pytest.approx(10 * LINE.char_time, abs=1e-6)
        await link.close()

    run_virtual(main())


def test_pacing_off_hands_bytes_over_on_the_next_turn_in_order() -> None:
    async def main() -> None:
        clock = current_clock()
        link, device = await _pair(pacing=False)
        start = clock.monotonic()
        for i in range(50):
            await link.write(bytes([i]))
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        assert bytes(device.received) == bytes(range(50))
        assert clock.monotonic() == start
        await link.close()

    run_virtual(main())


def test_modem_lines_travel_both_ways_as_events() -> None:
    async def main() -> None:
        clock = current_clock()
        link, device = await _pair()
        port = device.port
        assert port is not None and link.has_modem_lines
        assert not await link.cts() and not await link.dsr()
        assert port.cts and port.dsr  # a host port asserts RTS and DTR when opened
        clock.call_at(clock.monotonic() + 3.0, port.set_rts, True)
        start = clock.monotonic()
        await link.wait_cts(True, timeout=10)
        assert clock.monotonic() - start == 3.0  # woken by the change, not by a poll
        port.set_dtr(True)
        assert await link.dsr()
        link.set_rts(False)
        link.set_dtr(False)
        assert not port.cts and not port.dsr
        start = clock.monotonic()
        with pytest.raises(LinkTimeout, match="CTS did not go low"):
            await link.wait_cts(False, timeout=2.5)
        assert clock.monotonic() - start == 2.5
        await link.close()

    run_virtual(main())


def test_one_host_at_a_time_and_a_new_session_after_a_close() -> None:
    async def main() -> None:
        sessions: list[Device] = []

        def connect(port: MemPort) -> None:
            sessions.append(Device())
            sessions[-1].attach(port)

        listen_mem("robot1", LINE, connect)
        first = await open_link("mem://robot1", LINE)
        with pytest.raises(MachineInUse, match="mem://robot1 is in use"):
            await open_link("mem://robot1", LINE)
        await first.write(b"bye")
        await first.close()
        second = await open_link("mem://robot1", LINE)  # free again at once
        await second.write(b"hi")
        await asyncio.sleep(1)
        assert [bytes(s.received) for s in sessions] == [b"bye", b"hi"]
        # The first session heard the close only after its bytes were through.
        assert sessions[0].closed_at is not None and sessions[1].closed_at is None
        assert sessions[0].closed_at >= sessions[0].arrivals[-1][0]
        await second.close()

    run_virtual(main())


def test_a_dropped_line_loses_what_was_in_flight_and_a_closed_one_keeps_it() -> None:
    async def main() -> None:
        link, device = await _pair(name="dropper")
        assert device.port is not None
        device.port.write(b"lost on the wire")
        device.port.drop()
        with pytest.raises(LinkClosed):
            await link.read(timeout=5)
        assert link.pending() == b""
        link2, device2 = await _pair(name="closer")
        assert device2.port is not None
        device2.port.write(b"all of it")
        device2.port.close()
        assert await link2.read_exactly(9, timeout=5) == b"all of it"
        with pytest.raises(LinkClosed):
            await link2.read(timeout=5)
        with pytest.raises(LinkClosed):
            await link2.write(b"x")
        # A host that closed hears nothing more: what was crossing toward it is not received.
        trace = TrafficLog(None)
        device3 = Device()
        listen_mem("leaver", LINE, device3.attach)
        link3 = await open_link("mem://leaver", LINE, trace=trace)
        assert device3.port is not None
        device3.port.write(b"too late")
        await link3.close()
        device3.port.write(b"later still")
        await asyncio.sleep(1)
        assert trace.received() == b"" and device3.closed_at is not None

    run_virtual(main())


def test_bad_urls_names_and_framing_are_refused_before_a_byte() -> None:
    async def main() -> None:
        with pytest.raises(LinkError, match="nothing listens there"):
            await open_link("mem://nobody", LINE)
        # "socket://[": the URL parser's own error comes out as a UsageError for every scheme.
        bad = ("mem://", "mem://a/b", "mem://a?x=1", "mem://bad name", "mem://" + "x" * 200)
        for url in (*bad, "mem://[", "socket://["):
            with pytest.raises(UsageError):
                await open_link(url, LINE)
        listen_mem("cnc1", LINE, lambda port: None)
        assert listening() == ["mem://cnc1"]
        with pytest.raises(UsageError, match="already listening"):
            listen_mem("cnc1", LINE, lambda port: None)
        with pytest.raises(UsageError, match="every byte would garble"):
            await open_link("mem://cnc1", LineSettings(9600, 8, "N", 1))
        # RTS/CTS handshaking is the host's choice, not the framing: that one opens.
        link = await open_link("mem://cnc1", LINE.with_(rtscts=True))
        await link.close()

    run_virtual(main())
    assert mem_name("mem://cnc-1.a_b") == "cnc-1.a_b"


async def test_a_mem_line_on_the_real_loop_and_clock_is_paced_too() -> None:
    """The same link on the standard loop: real time, the trace logs both ways."""
    fast = LineSettings(115200, 8, "N", 1)
    trace = TrafficLog(None)
    device = Device()
    listener = listen_mem("real1", fast, device.attach)
    link = await open_link("mem://real1", fast, trace=trace, label="real1")
    assert device.port is not None
    device.port.write(b"\x11ready\r\n")
    assert await link.read_until(b"\r\n", timeout=2) == b"\x11ready\r\n"
    await link.write(b"000 G0 X1\r\n")
    deadline = asyncio.get_running_loop().time() + 2
    while bytes(device.received) != b"000 G0 X1\r\n":
        assert asyncio.get_running_loop().time() < deadline, "the bytes did not arrive"
        await asyncio.sleep(0.001)
    assert trace.sent("real1") == b"000 G0 X1\r\n"
    assert trace.received("real1") == b"\x11ready\r\n"
    await link.close()
    listener.close()
    with pytest.raises(LinkError, match="nothing listens"):
        await open_link("mem://real1", fast)


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=60))
def test_any_mem_url_opens_or_is_refused_with_a_typed_error(rest: str) -> None:
    url = "mem://" + rest

    async def main() -> None:
        listen_mem("known", LINE, lambda port: None)
        try:
            link = await open_link(url, LINE)
        except (UsageError, LinkError) as e:
            assert str(e)
        else:
            assert url == "mem://known"
            await link.close()

    run_virtual(main())
