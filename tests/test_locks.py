"""One owner per machine and per cell, as a user meets it: a second process is refused (exit 6)
with the holder named, before it opens the link or sends a byte; a lock left by a killed
process is taken over; the cell's files are private."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

from cellctl.cell.journal import JOURNAL_FILE, open_journal
from cellctl.cell.owner import acquire_controller_lock, controller_holder
from cellctl.drivers.state import StateStore
from cellctl.errors import MachineInUse, UsageError
from cellctl.kinds.ibm7545.driver import Ibm7545Robot
from cellctl.link import open_link
from cellctl.link.keys import link_lock_paths
from cellctl.link.lock import (
    RUNTIME_ENV,
    SYSTEM_LOCK_DIR,
    Holder,
    OwnerLock,
    advice,
    default_process_label,
    holder,
    runtime_dir,
    set_process_label,
)
from cellctl.mailbox import MAILBOX_FILE, open_mailbox
from cellctl.service.rpc import SOCKET_FILE
from cellctl.ui.cell_cli import run_controller

from .conftest import CELLCTL, Served

LABEL = "cellctl console"


@pytest.fixture
def label() -> Iterator[str]:
    """This test process names itself as the operator console does in its lock records."""
    set_process_label(LABEL)
    yield LABEL
    set_process_label(None)


async def cellctl(*args: str) -> tuple[int, str]:
    """Run the CLI in its own process without blocking this loop (the emulator runs here)."""
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, *args, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    async with asyncio.timeout(60):
        _, err = await proc.communicate()
    assert proc.returncode is not None
    return proc.returncode, err.decode()


async def bytes_received(served: Served, at_least: int) -> int:
    """The host bytes the emulator has received, once it has at least ``at_least`` (bytes
    cross the pty or socket after the driver's write returns: poll, as the emulator's line
    has no event for it), or after 5 s."""
    line = served.server.current_line
    assert line is not None
    deadline = asyncio.get_running_loop().time() + 5.0
    while line.bytes_in < at_least and asyncio.get_running_loop().time() < deadline:  # noqa: ASYNC110
        await asyncio.sleep(0.005)
    return line.bytes_in


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


# -- machines -------------------------------------------------------------------------------------


async def test_second_process_by_link_is_refused_before_a_byte(
    robot_served: Served, tmp_path: Path, label: str
) -> None:
    async with await Ibm7545Robot.connect(robot_served.url) as robot:
        await robot.status()
        line = robot_served.server.current_line
        code, err = await cellctl(
            "--cell", str(tmp_path), "robot", "--link", robot_served.url, "status"
        )
        assert code == 6, err
        assert f"{robot_served.url} is in use by {label} (pid {os.getpid()}) since" in err
        assert "use that console, or close it" in err  # the holder is a console
        await robot.status()  # the owner carries on
        # The emulator saw nothing of the refused process: the same host connection, and
        # every byte it received is one the owner sent.
        assert robot_served.server.current_line is line
        assert await bytes_received(robot_served, robot.link.bytes_sent) == robot.link.bytes_sent


async def test_another_spelling_of_the_link_is_refused_before_a_byte(
    robot_served: Served, tmp_path: Path, label: str
) -> None:
    """localhost and 127.0.0.1 are one endpoint (a pty: its /dev/pts//N spelling)."""
    if robot_served.url.startswith("/dev/"):
        number = robot_served.url.rsplit("/", 1)[1]
        other = f"/dev/pts//{number}"
    else:
        other = robot_served.url.replace("127.0.0.1", "localhost")
    async with await Ibm7545Robot.connect(robot_served.url) as robot:
        await robot.status()
        line = robot_served.server.current_line
        code, err = await cellctl("--cell", str(tmp_path), "robot", "--link", other, "status")
        assert code == 6, err
        assert f"{other} is in use by {label} (pid {os.getpid()}) since" in err
        await robot.status()
        assert robot_served.server.current_line is line
        assert await bytes_received(robot_served, robot.link.bytes_sent) == robot.link.bytes_sent


async def test_a_link_lock_is_seen_whatever_the_environment(
    robot_served: Served, tmp_path: Path, label: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A login shell has $XDG_RUNTIME_DIR, the cell's systemd service has none and a private
    /tmp: the link locks live where both see them."""
    if not os.access(SYSTEM_LOCK_DIR, os.W_OK | os.X_OK):
        pytest.skip(f"{SYSTEM_LOCK_DIR} is not writable here: the runtime dir falls back")
    # This process too, as a user's shell would: without the tests' own runtime dir.
    monkeypatch.delenv(RUNTIME_ENV)
    clean = {k: v for k, v in os.environ.items() if k not in (RUNTIME_ENV, "XDG_RUNTIME_DIR")}
    own = tmp_path / "xdg"
    own.mkdir(mode=0o700)
    for env in (clean, {**clean, "XDG_RUNTIME_DIR": str(own)}):
        proc = await asyncio.create_subprocess_exec(
            *CELLCTL, "emulate", "robot", "--listen", "socket://127.0.0.1:0", "--no-pacing",
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
        )  # fmt: skip
        try:
            assert proc.stdout is not None
            async with asyncio.timeout(30):
                said = (await proc.stdout.readline()).decode()
            url = said.split("listening on ", 1)[1].split()[0]
            async with await Ibm7545Robot.connect(url) as robot:
                await robot.status()
                other = await asyncio.create_subprocess_exec(
                    *CELLCTL, "--cell", str(tmp_path), "robot", "--link", url, "status",
                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                )  # fmt: skip
                async with asyncio.timeout(60):
                    _, err = await other.communicate()
                assert other.returncode == 6, err.decode()
                assert f"{url} is in use by {label}" in err.decode()
        finally:
            proc.terminate()
            async with asyncio.timeout(10):
                await proc.wait()


async def test_second_process_by_name_is_refused(
    robot_served: Served, tmp_path: Path, label: str
) -> None:
    (tmp_path / "cell.toml").write_text(
        f'[machines.robot1]\nkind = "ibm7545"\nlink = "{robot_served.url}"\n'
    )
    store = StateStore(tmp_path)
    async with await Ibm7545Robot.connect(robot_served.url, name="robot1", store=store) as robot:
        await robot.status()
        line = robot_served.server.current_line
        code, err = await cellctl("--cell", str(tmp_path), "robot", "robot1", "status")
        assert code == 6, err
        assert f"robot1 is in use by {label} (pid {os.getpid()}) since" in err
        assert robot_served.server.current_line is line
        assert await bytes_received(robot_served, robot.link.bytes_sent) == robot.link.bytes_sent
        assert mode(store.lock_path("robot1")) == 0o600  # the lock file is private
    # Closed: the next owner gets it at once; the lock file went with its owner.
    assert not store.lock_path("robot1").exists()
    code, err = await cellctl("--cell", str(tmp_path), "robot", "robot1", "status")
    assert code == 0, err


async def test_second_driver_in_the_same_process_is_refused(
    robot_served: Served, tmp_path: Path
) -> None:
    store = StateStore(tmp_path)
    first = await Ibm7545Robot.connect(robot_served.url, name="robot1", store=store)
    with pytest.raises(MachineInUse, match=r"robot1 is in use by .*\(pid \d+\)"):
        await Ibm7545Robot.connect(robot_served.url, name="robot1", store=store)
    with pytest.raises(MachineInUse, match="is in use by"):  # same link under another name
        await Ibm7545Robot.connect(robot_served.url, name="robot2", store=store)
    await first.close()
    # Closing gave both locks back: a reopen (as after a dropped link) succeeds.
    async with await Ibm7545Robot.connect(robot_served.url, name="robot1", store=store) as again:
        await again.status()


async def test_device_held_exclusively_elsewhere_is_machine_in_use(
    tmp_path: Path,
) -> None:
    master, slave = os.openpty()
    device = os.ttyname(slave)
    try:
        # Another program holding the device exclusively (pyserial's exclusive=True: flock).
        other = serial.Serial(device, exclusive=True, timeout=0)
        try:
            with pytest.raises(MachineInUse, match=f"{device} is in use"):
                await open_link(device)
        finally:
            other.close()
        link = await open_link(device)
        await link.close()
    finally:
        os.close(master)
        os.close(slave)


# -- stale and garbage lock files -----------------------------------------------------------------

HOLD = """
import sys
from cellctl.link.lock import OwnerLock, set_process_label
set_process_label("stale child")
lock = OwnerLock.acquire(sys.argv[1], "cnc1")
print("held", flush=True)
sys.stdin.read()
"""


def test_lock_of_a_killed_process_is_taken_over(tmp_path: Path, label: str) -> None:
    path = tmp_path / "state" / "machine-cnc1.lock"
    child = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(path)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout is not None
        assert child.stdout.readline() == "held\n"
        held = holder(path)
        assert held is not None and held.pid == child.pid and held.command == "stale child"
        with pytest.raises(MachineInUse) as refused:
            OwnerLock.acquire(path, "cnc1")
        assert str(refused.value).startswith(f"cnc1 is in use by stale child (pid {child.pid})")
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
    # The killed owner's record is still in the file, but nobody holds the lock.
    assert json.loads(path.read_text())["pid"] == child.pid
    assert holder(path) is None
    with OwnerLock.acquire(path, "cnc1"):
        now = holder(path)
        assert now is not None and now.pid == os.getpid() and now.command == label
        assert mode(path) == 0o600
    assert holder(path) is None


def test_lock_file_with_garbage_is_taken_over(tmp_path: Path, label: str) -> None:
    path = tmp_path / "link-x.lock"
    path.write_bytes(b'\x00\xff{"pid": garbage' + b"x" * 5000)
    assert holder(path) is None
    with OwnerLock.acquire(path, "x"):
        now = holder(path)
        assert now is not None and now.pid == os.getpid() and now.command == label


def test_process_label_from_the_command_line() -> None:
    argv = ["/venv/bin/cellctl", "--cell", "c1", "robot", "--link", "/dev/pts/4", "status"]
    assert default_process_label(argv) == "cellctl robot status"
    assert default_process_label(["/venv/bin/cellctl", "--cell=c1", "run", "--no-live"]) == (
        "cellctl run"
    )


def test_runtime_dir_is_private_and_refuses_a_foreign_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(RUNTIME_ENV, str(tmp_path / "cellctl"))
    made = runtime_dir()
    assert made == tmp_path / "cellctl" and mode(made) == 0o700
    made.rmdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    made.symlink_to(elsewhere)  # planted by someone else: not a directory of ours
    with pytest.raises(UsageError, match="should be a directory"):
        runtime_dir()
    if os.getuid() == 0:  # only root can give a directory away
        made.unlink()
        made.mkdir()
        os.chown(made, 4321, -1)
        with pytest.raises(UsageError, match="belongs to uid 4321"):
            runtime_dir()


# -- the cell controller --------------------------------------------------------------------------


EXAMPLE_CELL = Path(__file__).resolve().parent.parent / "examples" / "cell" / "cell.toml"


@pytest.fixture
def example_cell(tmp_path: Path) -> Path:
    """A cell directory with the laboratory's cell.toml, and nothing else yet."""
    (tmp_path / "cell.toml").write_text(EXAMPLE_CELL.read_text())
    return tmp_path


async def test_second_controller_is_refused_and_touches_nothing(
    example_cell: Path, label: str
) -> None:
    tmp_path = example_cell
    with acquire_controller_lock(tmp_path):
        running = controller_holder(tmp_path)
        assert running is not None and running.pid == os.getpid()
        code, err = await cellctl("--cell", str(tmp_path), "run", "--no-live")
        assert code == 6, err
        assert f"the cell in {tmp_path} is already run by {label} (pid {os.getpid()}) since" in err
        with pytest.raises(MachineInUse, match="is already run by"):
            await run_controller(tmp_path, live=False, until_idle=True)
        # Neither refused controller opened the journal or the mailbox.
        assert not (tmp_path / JOURNAL_FILE).exists()
        assert not (tmp_path / MAILBOX_FILE).exists()
    assert controller_holder(tmp_path) is None


async def test_a_controller_refused_a_held_machine_serves_nothing_and_opens_nothing(
    tmp_path: Path, label: str
) -> None:
    """A console standalone holds cnc1's link: ``cellctl run`` is refused with the holder
    named before it serves its API, opens the journal or the mailbox, or takes a lock."""
    tmp_path = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL.parent, tmp_path)
    with OwnerLock.acquire(StateStore(tmp_path).lock_path("cnc1"), "cnc1"):
        code, err = await cellctl("--cell", str(tmp_path), "run", "--no-live")
        assert code == 6, err
        assert f"cnc1 is in use by {label} (pid {os.getpid()}) since" in err, err
        assert "control API on" not in err
        assert not (tmp_path / SOCKET_FILE).exists()
        assert not (tmp_path / JOURNAL_FILE).exists()
        assert not (tmp_path / MAILBOX_FILE).exists()
        assert holder(StateStore(tmp_path).lock_path("robot")) is None
    # The PLC's link, held by URL (a `cellctl plc` session): the same.
    plc_url = tomllib.loads((tmp_path / "cell.toml").read_text())["plc"]["url"]
    (plc_lock,) = link_lock_paths(plc_url)
    with OwnerLock.acquire(plc_lock, plc_url):
        with pytest.raises(MachineInUse, match=f"{plc_url} is in use by {label}"):
            await run_controller(tmp_path, live=False, until_idle=True)
        assert not (tmp_path / JOURNAL_FILE).exists()


def test_controller_lock_refuses_a_missing_cell(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="no such cell directory"):
        acquire_controller_lock(tmp_path / "typo")
    assert not (tmp_path / "typo").exists()


# -- private files --------------------------------------------------------------------------------


def test_journal_mailbox_and_state_files_are_private(tmp_path: Path) -> None:
    old = os.umask(0o022)  # a usual umask, which would leave files world-readable
    try:
        with open_journal(tmp_path), open_mailbox(tmp_path) as mailbox:
            mailbox.post_order("wax-robot-base", 1)
            store = StateStore(tmp_path)
            store.save("robot1", {"state": 1})
            lock = OwnerLock.acquire(store.lock_path("robot1"), "robot1")
            files = [
                tmp_path / JOURNAL_FILE,
                tmp_path / MAILBOX_FILE,
                tmp_path / f"{MAILBOX_FILE}-wal",
                tmp_path / f"{MAILBOX_FILE}-shm",
                store.path("robot1"),
                store.lock_path("robot1"),
            ]
            assert {f.name: mode(f) for f in files} == {f.name: 0o600 for f in files}
            assert mode(store.dir) == 0o700
            lock.release()
            assert not store.lock_path("robot1").exists()  # given back: nothing left behind
        # A file left looser (an older cellctl, a copy) is tightened when opened.
        os.chmod(tmp_path / JOURNAL_FILE, 0o644)
        open_journal(tmp_path).close()
        assert mode(tmp_path / JOURNAL_FILE) == 0o600
    finally:
        os.umask(old)


@pytest.mark.parametrize(
    ("command", "said"),
    [
        ("cellctl run", "use `cellctl console` or the API"),
        ("cellctl dnc serve", "use `cellctl console` or the API"),
        ("cellctl console", "use that console, or close it"),
        ("cellctl robot download 4", "wait for it to end, or end it where it runs"),
        ("cellctl dnc drip", "wait for it to end, or end it where it runs"),
    ],
)
def test_a_refusal_says_what_works_with_its_holder(command: str, said: str) -> None:
    # A one-off command serves no API to ask: "use the API" would send the user nowhere.
    holder = Holder(4242, command, 0.0, "")
    assert advice(holder).startswith(said)
