"""Wrong OPC UA logins are held back per client address: a guesser locks out the names it
guesses from its own address, and its address once it guesses widely, but nobody elsewhere.
The defect: a name's wrong logins from anywhere locked that name out everywhere, and 30
wrong logins of any names locked every user out for the minute, so one client could keep a
factory's OPC UA users out for good.

Through real sockets: an asyncua server with the cell's user manager on loopback, clients
connecting straight (from 127.0.0.1) and through a relay whose connection comes from
127.0.0.2, as a second machine's would."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from asyncua import Client, Server, ua
from asyncua.ua.uaerrors import BadUserAccessDenied

from cellctl.factory.opcua.users import (
    LOGIN_FAILURES,
    LOGIN_FAILURES_ALL,
    LOGIN_FLOOD,
    FileUserManager,
    add_user,
    login_from,
    track_peers,
)

#: A hang guard for one login, not a timing figure.
LOGIN_S = 20.0
ALICE = ("alice", "correct horse")


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    with contextlib.suppress(OSError):
        while data := await reader.read(65536):
            writer.write(data)
            await writer.drain()
    writer.close()


@contextlib.asynccontextmanager
async def relay(port: int, source: str) -> AsyncIterator[int]:
    """A port on 127.0.0.1 whose connections reach ``port`` from address ``source``."""

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_r, up_w = await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0))
        await asyncio.gather(_pipe(reader, up_w), _pipe(up_r, writer))

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    async with server:
        yield server.sockets[0].getsockname()[1]


@contextlib.asynccontextmanager
async def opcua_server(users: Path, said: list[str]) -> AsyncIterator[int]:
    """An OPC UA server on a free loopback port whose logins the users file decides."""
    manager = FileUserManager(
        users, anonymous_read=False, refused=lambda name, peer: said.append(f"{name} {peer}")
    )
    server = Server(user_manager=manager)  # type: ignore[arg-type]
    track_peers(server)
    await server.init()
    server.set_endpoint("opc.tcp://127.0.0.1:0/")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    server.set_identity_tokens([ua.UserNameIdentityToken])
    async with server:
        yield server.bserver._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]


async def login(port: int, name: str, password: str) -> bool:
    """True if ``name`` logs in with ``password`` on 127.0.0.1:``port``; False if refused."""
    client = Client(f"opc.tcp://127.0.0.1:{port}/", timeout=LOGIN_S)
    client.set_user(name)
    client.set_password(password)
    try:
        async with asyncio.timeout(LOGIN_S), client:
            return True
    except BadUserAccessDenied:
        return False


async def test_a_guesser_elsewhere_locks_nobody_out(tmp_path: Path) -> None:
    users = tmp_path / "opcua-users.toml"
    add_user(users, *ALICE)
    said: list[str] = []
    async with opcua_server(users, said) as port, relay(port, "127.0.0.2") as elsewhere:
        for _ in range(LOGIN_FAILURES):
            assert not await login(elsewhere, "alice", "guess")
        assert not await login(elsewhere, *ALICE)  # held back there, its right password too
        assert await login(port, *ALICE)  # alice at her own machine still logs in
        # The guesser tries every name it can think of: its address is held back as a whole.
        for i in range(LOGIN_FAILURES_ALL - LOGIN_FAILURES):
            assert not await login(elsewhere, f"name{i}", "guess")
        assert not await login(elsewhere, "bob", "anything")
        assert await login(port, *ALICE)
    assert said[:LOGIN_FAILURES] == ["alice 127.0.0.2"] * LOGIN_FAILURES
    assert len(said) == LOGIN_FAILURES_ALL  # each held-back try unchecked and unlogged


def test_a_flood_holds_back_only_the_addresses_that_took_part(tmp_path: Path) -> None:
    """Past LOGIN_FLOOD wrong logins from all addresses together (a password hash each would
    stall the server's loop), an address with a wrong login in the window waits it out; an
    address with none is still checked."""
    from cellctl.clock import current_clock, run_virtual
    from cellctl.factory.opcua.users import LOGIN_WINDOW_S

    users = tmp_path / "opcua-users.toml"
    add_user(users, *ALICE)
    manager = FileUserManager(users, anonymous_read=False)

    async def logins() -> None:
        for i in range(LOGIN_FLOOD):
            with login_from(f"10.0.{i // 4}.1"):  # 4 wrong logins each: none held back alone
                assert manager.get_user(None, f"name{i % 4}", "guess") is None
        with login_from("10.0.0.1"):
            assert manager.get_user(None, *ALICE) is None  # took part: waits the window out
        with login_from("10.9.9.9"):
            assert manager.get_user(None, *ALICE) is not None
        await current_clock().sleep(LOGIN_WINDOW_S)
        with login_from("10.0.0.1"):
            assert manager.get_user(None, *ALICE) is not None

    run_virtual(logins())


@pytest.mark.parametrize("failures", [LOGIN_FAILURES - 1])
def test_fewer_wrong_logins_than_the_limit_hold_nothing_back(tmp_path: Path, failures: int) -> None:
    users = tmp_path / "opcua-users.toml"
    add_user(users, *ALICE)
    manager = FileUserManager(users, anonymous_read=False)
    with login_from("10.0.0.1"):
        for _ in range(failures):
            assert manager.get_user(None, "alice", "guess") is None
        assert manager.get_user(None, *ALICE) is not None
