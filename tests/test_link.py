"""The link layer over every transport, against real ptys and sockets."""

from __future__ import annotations

import asyncio
import io
import os
from pathlib import Path

import pytest

from cellctl.emulators.serve import DeviceLine, EmulatedDevice, serve
from cellctl.errors import LinkClosed, LinkError, LinkTimeout, UsageError
from cellctl.link import ROBOT_LINE, LineSettings, TrafficLog, open_link

from .conftest import TRANSPORTS, Ser2net, listen_url


class Echo(EmulatedDevice):
    """Answers every line upper-cased; a line "RTS1"/"RTS0" sets its RTS."""

    def __init__(self) -> None:
        self.settings_seen: list[LineSettings] = []

    async def session(self, line: DeviceLine) -> None:
        while True:
            data = await line.read_until(b"\n")
            if data.startswith(b"RTS"):
                line.set_rts(data[3:4] == b"1")
            await line.write(data.upper())

    def line_changed(self, line: DeviceLine) -> None:
        self.settings_seen.append(line.settings)


def test_line_settings_parse_and_rate() -> None:
    s = LineSettings.parse("4800,7E2")
    assert s == ROBOT_LINE and str(s) == "4800,7E2"
    assert s.bits_per_char == 11
    assert round(s.chars_per_second, 2) == 436.36
    assert LineSettings.parse("2400,8N1,rtscts").rtscts
    for bad in ("4800", "4800,9E2", "fast", "4800,7X2"):
        with pytest.raises(UsageError):
            LineSettings.parse(bad)


async def test_loop_link_reads_back_what_it_writes() -> None:
    async with await open_link("loop://") as link:
        await link.write(b"abc\r\nrest")
        assert await link.read_until(b"\r\n", timeout=1) == b"abc\r\n"
        assert await link.read_exactly(4, timeout=1) == b"rest"
        with pytest.raises(LinkTimeout, match="no answer in time"):
            await link.read(timeout=0.01)


async def test_unknown_url_and_unreachable_host_are_refused() -> None:
    with pytest.raises(UsageError, match="not understood"):
        await open_link("ftp://example")
    with pytest.raises(UsageError, match="HOST:PORT"):
        await open_link("socket://localhost")
    # In the system's words, once: not asyncio's "Connect call failed", not pyserial's errno
    # told twice.
    with pytest.raises(LinkError) as refused:
        await open_link("socket://127.0.0.1:1")
    assert str(refused.value) == "cannot connect to socket://127.0.0.1:1: connection refused"
    with pytest.raises(LinkError) as missing:
        await open_link("/dev/does-not-exist")
    assert str(missing.value) == (
        "cannot open serial port /dev/does-not-exist: no such file or directory"
    )


async def test_a_machine_whose_link_cannot_be_opened_is_named(tmp_path: Path) -> None:
    """A cell of several machines says which one it could not reach (``cellctl run``)."""
    from cellctl.cell.machines import open_machine
    from cellctl.link import MILL_LINE

    with pytest.raises(LinkError) as refused:
        await open_machine(
            "dyna2400", "cnc2", "rfc2217://127.0.0.1:1", MILL_LINE, {}, store=None, trace=None
        )
    assert str(refused.value) == "cnc2: cannot connect to rfc2217://127.0.0.1:1: connection refused"


@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_every_byte_value_travels_both_ways(transport: str) -> None:
    server = await serve(Echo(), listen_url(transport), ROBOT_LINE, pacing=False)
    payload = bytes(b for b in range(256) if b != 0x0A) + b"\n"
    try:
        async with await open_link(server.url, ROBOT_LINE) as link:
            await link.write(payload)
            got = await link.read_until(b"\n", timeout=5)
        assert got == payload.upper()
    finally:
        await server.close()


@pytest.mark.parametrize("transport", ["socket", "rfc2217"])
async def test_a_burst_many_times_the_read_buffer_travels_whole_and_in_order(
    transport: str,
) -> None:
    # TCP links and emulated TCP lines read 4 KiB at a time: 100 KiB at once must still come
    # through whole, both ways, in order. (An emulated pty drops what overflows the tty
    # buffer, a few KiB; records are far smaller.)
    server = await serve(Echo(), listen_url(transport), ROBOT_LINE, pacing=False)
    payload = bytes(b"abcdefghijklmnopqrstuvwxyz"[i % 26] for i in range(100_000)) + b"\n"
    try:
        async with await open_link(server.url, ROBOT_LINE) as link:
            await link.write(payload)
            got = await link.read_exactly(len(payload), timeout=10)
        assert got == payload.upper()
    finally:
        await server.close()


@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_paced_line_never_delivers_early(transport: str) -> None:
    server = await serve(Echo(), listen_url(transport), ROBOT_LINE, pacing=True)
    try:
        async with await open_link(server.url, ROBOT_LINE) as link:
            loop = asyncio.get_running_loop()
            start = loop.time()
            await link.write(b"x" * 20 + b"\n")
            await link.read_until(b"\n", timeout=5)
            elapsed = loop.time() - start
        # 21 characters each way at 4800 7E2 cannot cross in less than their wire time.
        assert elapsed >= 2 * ROBOT_LINE.wire_time(21) * 0.99
    finally:
        await server.close()


async def test_rfc2217_carries_cts_and_line_settings() -> None:
    echo = Echo()
    server = await serve(echo, "rfc2217://127.0.0.1:0", ROBOT_LINE, pacing=False)
    try:
        settings = LineSettings.parse("2400,8N1")
        async with await open_link(server.url, settings) as link:
            assert link.has_modem_lines
            assert await link.cts() is False
            await link.write(b"RTS1\n")
            await link.read_until(b"\n", timeout=2)
            await link.wait_cts(True, timeout=2)
            assert await link.cts() is True
            await link.write(b"RTS0\n")
            await link.wait_cts(False, timeout=2)
        assert echo.settings_seen[-1].baudrate == 2400
        assert echo.settings_seen[-1].parity == "N"
    finally:
        await server.close()


async def test_rfc2217_client_refuses_a_raw_server() -> None:
    server = await serve(Echo(), "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    try:
        port = server.url.rsplit(":", 1)[1]
        with pytest.raises(LinkError, match="RFC 2217"):
            await open_link(f"rfc2217://127.0.0.1:{port}", connect_timeout=0.5)
    finally:
        await server.close()


async def test_rfc2217_through_real_ser2net(ser2net_available: None, tmp_path: Path) -> None:
    server = await serve(Echo(), "pty", ROBOT_LINE, pacing=False)
    proxy = Ser2net(server.url, "4800e72", tmp_path)
    try:
        await proxy.wait_listening()
        async with await open_link(proxy.url, ROBOT_LINE) as link:
            await link.write(b"hello \xff\n")
            assert await link.read_until(b"\n", timeout=5) == b"HELLO \xff\n"
            assert isinstance(await link.cts(), bool)
    finally:
        proxy.stop()
        await server.close()


@pytest.mark.parametrize("transport", ["pty", "socket"])
async def test_links_without_modem_lines_refuse_cts(transport: str) -> None:
    server = await serve(Echo(), listen_url(transport), ROBOT_LINE, pacing=False)
    try:
        async with await open_link(server.url) as link:
            assert not link.has_modem_lines
            with pytest.raises(UsageError, match="modem lines"):
                await link.cts()
    finally:
        await server.close()


async def test_closed_by_the_other_end_is_link_closed() -> None:
    server = await serve(Echo(), "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    link = await open_link(server.url)
    await link.write(b"ping\n")
    await link.read_until(b"\n", timeout=2)
    await server.close()
    with pytest.raises(LinkClosed):
        await link.read(timeout=2)
    await link.close()


async def test_traffic_log_records_both_directions() -> None:
    out = io.StringIO()
    log = TrafficLog(out)
    server = await serve(Echo(), "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    try:
        async with await open_link(server.url, trace=log, label="robot1") as link:
            await link.write(b"R\x13\n")
            await link.read_until(b"\n", timeout=2)
    finally:
        await server.close()
    assert log.sent("robot1") == b"R\x13\n"
    assert log.received("robot1") == b"R\x13\n"
    text = out.getvalue()
    assert "robot1 >>  52 13 0A" in text and "|R..|" in text
    assert "robot1 <<" in text


async def test_300_simultaneous_pty_links_in_one_process() -> None:
    count = 300
    servers = [await serve(Echo(), "pty", ROBOT_LINE, pacing=False) for _ in range(count)]
    links = [await open_link(s.url, ROBOT_LINE) for s in servers]
    try:
        # Beyond descriptor 1024 select() would fail; the event loop's epoll must not.
        assert max(link._fd for link in links) > 1024  # type: ignore[attr-defined]

        async def ping(i: int) -> bytes:
            await links[i].write(f"link {i}\n".encode())
            return await links[i].read_until(b"\n", timeout=20)

        replies = await asyncio.gather(*(ping(i) for i in range(count)))
        assert replies == [f"LINK {i}\n".encode() for i in range(count)]
    finally:
        for link in links:
            await link.close()
        for s in servers:
            await s.close()
    assert os.get_blocking(0) in (True, False)  # the process is still healthy
