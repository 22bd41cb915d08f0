"""Which links are one link (cellctl.link.keys): every spelling of one endpoint has the same
canonical keys and the same owner lock files, whatever the URL says; a name that does not
resolve is refused in words, and nothing a user writes as a link makes anything but a typed
error come out."""

from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.drivers.state import machine_key
from cellctl.errors import LinkError, MachineInUse, UsageError
from cellctl.kinds.ibm7545.driver import Ibm7545Robot
from cellctl.link.keys import link_keys, link_lock_paths, links_overlap, needs_lookup
from cellctl.link.lock import RUNTIME_ENV, OwnerLock, holder

#: A name under .invalid never resolves (RFC 6761): the resolver says so at once.
NOWHERE = "cellctl-test.invalid"


def addresses_of(host: str) -> set[str]:
    """What this machine resolves ``host`` to (its /etc/hosts decides: ::1 or not)."""
    return {str(info[4][0]) for info in socket.getaddrinfo(host, 1, type=socket.SOCK_STREAM)}


@pytest.fixture
def own_runtime_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """This test's own runtime directory for lock files (it and its children use it)."""
    directory = tmp_path / "run"
    monkeypatch.setenv(RUNTIME_ENV, str(directory))
    yield directory


# -- network links ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "spelling",
    [
        "rfc2217://localhost:17102",
        "rfc2217://LocalHost:17102",
        "socket://localhost:17102",
        "socket://127.0.0.1:017102",
        "socket://[::ffff:127.0.0.1]:17102",
        "modbus://localhost:17102",
        "rfc2217://127.0.0.1:17102?logging=debug",
    ],
)
def test_every_spelling_of_a_loopback_endpoint_is_the_same_link(spelling: str) -> None:
    assert "tcp://127.0.0.1:17102" in link_keys(spelling)
    assert links_overlap(spelling, "rfc2217://127.0.0.1:17102")
    assert not links_overlap(spelling, "rfc2217://127.0.0.1:17103")


def test_a_name_with_several_addresses_holds_them_all() -> None:
    keys = link_keys("socket://localhost:17110")
    expected = {
        f"tcp://[{a}]:17110" if ":" in a else f"tcp://{a}:17110" for a in addresses_of("localhost")
    }
    assert set(keys) == expected
    assert keys == tuple(sorted(keys))
    for key in keys:  # each address alone is the same link as the name
        address = key.removeprefix("tcp://").rsplit(":", 1)[0]
        assert links_overlap(f"socket://{address}:17110", "socket://localhost:17110")


def test_ipv6_addresses_are_canonical() -> None:
    assert link_keys("socket://[0:0:0:0:0:0:0:1]:7001") == ("tcp://[::1]:7001",)
    assert link_keys("socket://[::]:7001") == link_keys("socket://[::1]:7001")
    assert link_keys("socket://0.0.0.0:7001") == ("tcp://127.0.0.1:7001",)
    assert link_keys("modbus://127.0.0.1") == link_keys("modbus://127.0.0.1:502")


def test_a_name_that_does_not_resolve_is_refused_in_words() -> None:
    with pytest.raises(LinkError, match=f"cannot resolve the host '{NOWHERE}'"):
        link_keys(f"rfc2217://{NOWHERE}:4001")
    with pytest.raises(LinkError, match="cannot resolve"):
        link_lock_paths(f"socket://{NOWHERE}:4001")
    # A configuration check keys it by its name instead (case and the root dot aside).
    assert link_keys(f"socket://{NOWHERE.upper()}:4001", unresolved="name") == (
        f"tcp://{NOWHERE}:4001",
    )
    assert links_overlap(f"socket://{NOWHERE}:4001", f"rfc2217://{NOWHERE}:4001")
    assert not links_overlap(f"socket://{NOWHERE}:4001", "socket://127.0.0.1:4001")


def test_only_a_network_name_asks_the_name_server() -> None:
    """What a driver's connect resolves in a worker thread (a slow name server stalls that
    connection, not the loop's other machines): a host name, nothing else."""
    for url in (f"socket://{NOWHERE}:4001", "rfc2217://localhost:7001", "modbus://plc1.lan"):
        assert needs_lookup(url), url
    for url in (
        "socket://127.0.0.1:4001",
        "rfc2217://[::1]:7001",
        "modbus://10.0.0.5",
        "/dev/ttyUSB0",
        "serial:///dev/ttyS0",
        "mem://robot1",
        "loop://",
        "socket://127.0.0.1",  # no port: refused where the keys are made
    ):
        assert not needs_lookup(url), url


def held_in(directory: Path) -> list[Path]:
    """The lock files in ``directory`` someone holds."""
    return [path for path in directory.glob("*.lock") if holder(path) is not None]


async def test_a_connect_to_a_name_that_does_not_resolve_is_refused_and_holds_nothing(
    own_runtime_dir: Path,
) -> None:
    """A driver's connect resolves the name off the event loop: the loop's other tasks go
    on, the refusal is in words, and no lock is left taken."""
    ticks = 0

    async def ticker() -> None:
        nonlocal ticks
        while True:
            ticks += 1
            await asyncio.sleep(0)

    ticking = asyncio.create_task(ticker())
    try:
        with pytest.raises(LinkError, match=f"cannot resolve the host '{NOWHERE}'"):
            await Ibm7545Robot.connect(f"socket://{NOWHERE}:4001")
    finally:
        ticking.cancel()
    assert ticks > 0
    assert not held_in(own_runtime_dir)


@pytest.mark.parametrize(
    ("url", "said"),
    [
        ("socket://127.0.0.1", "write socket://HOST:PORT"),
        ("rfc2217://:4001", "write rfc2217://HOST:PORT"),
        ("socket://127.0.0.1:99999", "not understood"),
        ("socket://[::1:4001", "not understood"),
        ("serial:///dev/tty\x00S0", "NUL byte"),
        ("/dev/tty\x00S0", "NUL byte"),
    ],
)
def test_a_network_url_without_host_or_port_is_a_usage_error(url: str, said: str) -> None:
    with pytest.raises(UsageError, match=said):
        link_keys(url)


@settings(max_examples=200)
@given(
    scheme=st.sampled_from(["socket", "rfc2217", "modbus", "serial", "loop", "mem", "x"]),
    rest=st.text(st.characters(codec="utf-8"), max_size=40) | st.just("/dev/\x00"),
)
def test_any_link_text_gives_keys_or_a_typed_error(scheme: str, rest: str) -> None:
    """Whatever a user writes after the scheme: keys, or a UsageError/LinkError in words
    (never another exception, never a wait past the deadline)."""
    for unresolved in ("refuse", "name"):
        try:
            keys = link_keys(f"{scheme}://{rest}", timeout=1.0, unresolved=unresolved)  # type: ignore[arg-type]
        except (UsageError, LinkError) as e:
            assert str(e)
        else:
            assert keys and all(isinstance(k, str) for k in keys)


# -- device paths ----------------------------------------------------------------------------------


def test_device_path_spellings_share_a_key_and_keep_their_lock_name(
    tmp_path: Path, own_runtime_dir: Path
) -> None:
    master, slave = os.openpty()
    try:
        device = os.ttyname(slave)
        alias = tmp_path / "robot-port"
        alias.symlink_to(device)
        number = device.rsplit("/", 1)[1]
        spellings = [device, f"serial://{device}", str(alias), f"/dev/pts//{number}"]
        assert {link_keys(s) for s in spellings} == {(device,)}
        # The lock file a device always had: a lock taken before this change still counts.
        assert link_lock_paths(str(alias)) == [own_runtime_dir / f"link-{machine_key(device)}.lock"]
    finally:
        os.close(master)
        os.close(slave)


def test_lock_files_of_two_endpoints_are_apart(own_runtime_dir: Path) -> None:
    names = {
        path.name
        for url in ("socket://[::1]:7001", "socket://[::1:0]:7001", "socket://127.0.0.1:7001")
        for path in link_lock_paths(url)
    }
    assert len(names) == 3
    assert "link-tcp-127.0.0.1-7001.lock" in names


# -- one owner whatever the spelling ---------------------------------------------------------------

HOLD = """
import sys
from cellctl.link.keys import link_lock_paths
from cellctl.link.lock import OwnerLock, set_process_label
set_process_label("cellctl mill download")
locks = [OwnerLock.acquire(p, sys.argv[1]) for p in link_lock_paths(sys.argv[1])]
print("held", flush=True)
sys.stdin.read()
"""


@pytest.mark.parametrize(
    ("owner", "other"),
    [
        ("rfc2217://127.0.0.1:17102", "rfc2217://localhost:17102"),
        ("rfc2217://localhost:17102", "rfc2217://127.0.0.1:17102"),
        ("socket://localhost:17110", "socket://127.0.0.1:17110"),
        ("socket://127.0.0.1:17110", "rfc2217://localhost:17110"),
    ],
)
def test_another_spelling_of_a_held_link_is_refused_with_the_holder(
    owner: str, other: str, own_runtime_dir: Path
) -> None:
    child = subprocess.Popen(
        [sys.executable, "-c", HOLD, owner],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == "held"
        with pytest.raises(MachineInUse) as refused:
            for path in link_lock_paths(other):
                OwnerLock.acquire(path, other).release()
        said = str(refused.value)
        assert f"is in use by cellctl mill download (pid {child.pid})" in said
    finally:
        assert child.stdin is not None
        child.stdin.close()
        child.wait(10)
    # Given back: the other spelling takes it now.
    locks = [OwnerLock.acquire(path, other) for path in link_lock_paths(other)]
    for lock in locks:
        lock.release()
