"""A ser2net port another client holds, or whose device is gone: the refusal says so, in
the server's words.

ser2net serves a port to one client at a time (``max-connections: 1``, its default, as the
README advises); a second client (another host, a terminal program, a cellctl of another
user) is told "Port already in use" and disconnected. That used to reach the engineer as
"the other end closed the link: [Errno 32] Broken pipe".
"""

from __future__ import annotations

import asyncio
import subprocess
from pathlib import Path

import pytest

from cellctl.emulators.serve import serve
from cellctl.errors import LinkClosed
from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator
from cellctl.link import ROBOT_LINE, Link, open_link

from .conftest import Ser2net, free_port


class OneClientSer2net(Ser2net):
    """A real ser2net in RFC 2217 mode with its default of one client a port (no kick)."""

    def __init__(self, device: str, tmp: Path) -> None:
        self.port = free_port()
        conf = tmp / "ser2net.yaml"
        conf.write_text(
            "connection: &con1\n"
            f"  accepter: telnet(rfc2217),tcp,127.0.0.1,{self.port}\n"
            f"  connector: serialdev,{device},4800e72,local\n"
        )
        self.proc = subprocess.Popen(
            ["ser2net", "-n", "-d", "-c", str(conf), "-P", str(tmp / "ser2net.pid")],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        self.url = f"rfc2217://127.0.0.1:{self.port}"


#: Seconds ser2net may take to be done with wait_listening()'s probe connection.
FREED_S = 10.0


async def _first_client(url: str) -> Link:
    """The port's one client, once ser2net let go of its last one (the probe that saw it
    listening: until then it says "Port already in use" too)."""
    async with asyncio.timeout(FREED_S):
        while True:
            try:
                return await open_link(url, ROBOT_LINE, connect_timeout=5)
            except LinkClosed:
                await asyncio.sleep(0.1)


async def test_a_port_held_by_another_client_says_so(
    ser2net_available: None, tmp_path: Path
) -> None:
    server = await serve(Ibm7545Emulator(time_scale=200.0), "pty", ROBOT_LINE, pacing=False)
    proxy = OneClientSer2net(server.url, tmp_path)
    try:
        await proxy.wait_listening()
        async with await _first_client(proxy.url):
            with pytest.raises(LinkClosed) as refused:
                await open_link(proxy.url, ROBOT_LINE, connect_timeout=5)
        said = str(refused.value)
        assert "the server closed the connection as it opened" in said
        assert '"Port already in use"' in said
        assert "another client (another host, a terminal program) holds that port" in said
    finally:
        proxy.stop()
        await server.close()


async def test_a_port_whose_device_is_gone_says_the_servers_words(
    ser2net_available: None, tmp_path: Path
) -> None:
    server = await serve(Ibm7545Emulator(time_scale=200.0), "pty", ROBOT_LINE, pacing=False)
    proxy = OneClientSer2net(server.url, tmp_path)
    try:
        await proxy.wait_listening()
        await server.close()  # the adapter unplugged behind the server
        async with asyncio.timeout(FREED_S):
            while True:  # until ser2net let go of its probe: then it tries the device
                with pytest.raises(LinkClosed) as refused:
                    await open_link(proxy.url, ROBOT_LINE, connect_timeout=5)
                if "in use" not in str(refused.value):
                    break
                await asyncio.sleep(0.1)
        said = str(refused.value)
        assert "the server closed the connection as it opened" in said
        assert 'saying "Device open failure' in said
        assert "see to it at the server" in said
        assert "another client" not in said
    finally:
        proxy.stop()
