"""A cell directory others can write to must not give the engineer's token away: ``cellctl
run`` refuses one (or one owned by another user), and a client checks who listens on
``api.sock`` (SO_PEERCRED) before it sends a token there."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from cellctl.cell.owner import acquire_controller_lock
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.errors import AccessDenied
from cellctl.service.client import attach
from cellctl.service.token import ensure_default
from tests.test_sqlite_links import cellctl

NOBODY = 65534
AS_ROOT = pytest.mark.skipif(os.geteuid() != 0, reason="another user's process needs root")

#: A process that listens where api.sock is and keeps what it is sent.
IMPOSTOR = """
import socket, sys
path, caught = sys.argv[1], sys.argv[2]
server = socket.socket(socket.AF_UNIX)
server.bind(path)
server.listen(1)
print("listening", flush=True)
server.settimeout(20)
try:
    conn, _ = server.accept()
except TimeoutError:
    sys.exit(0)
conn.settimeout(3)
data = b""
try:
    while chunk := conn.recv(4096):
        data += chunk
except (TimeoutError, OSError):
    pass
open(caught, "wb").write(data)
"""


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    ensure_default(directory)
    return directory


@contextmanager
def impostor(cell: Path, user: int | None = None) -> Iterator[Path]:
    """A listener on ``cell/api.sock`` (run as ``user``); yields where it writes what it got."""
    caught = cell / "caught"
    proc = subprocess.Popen(
        [sys.executable, "-c", IMPOSTOR, str(cell / "api.sock"), str(caught)],
        stdout=subprocess.PIPE,
        text=True,
        user=user,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "listening\n"
        yield caught
    finally:
        try:
            proc.wait(timeout=10)  # it ends once its one connection has closed
        except subprocess.TimeoutExpired:
            proc.terminate()
            proc.wait(timeout=10)


@pytest.mark.parametrize(("mode", "who"), [(0o777, "every user"), (0o757, "every user")])
def test_run_refuses_a_cell_directory_others_can_write(cell: Path, mode: int, who: str) -> None:
    cell.chmod(mode)
    done = cellctl(cell, "run")
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"{cell} can be written by {who} (mode {mode:04o})" in done.stderr, done.stderr
    assert f"chmod go-w {cell}" in done.stderr and "Traceback" not in done.stderr
    assert not (cell / "state").exists() and not (cell / "journal.sqlite3").exists()


@AS_ROOT
def test_run_refuses_a_group_writable_directory_of_a_shared_group(cell: Path) -> None:
    os.chown(cell, -1, 100)  # "users": not root's own group
    cell.chmod(0o775)
    done = cellctl(cell, "run")
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"{cell} can be written by the group " in done.stderr, done.stderr


@AS_ROOT
def test_run_refuses_a_cell_directory_of_another_user(cell: Path) -> None:
    os.chown(cell, NOBODY, -1)
    done = cellctl(cell, "run")
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"{cell} belongs to nobody, not to root who runs `cellctl run`" in done.stderr
    assert not (cell / "state").exists()


async def test_no_token_is_sent_to_a_socket_the_controller_does_not_hold(cell: Path) -> None:
    """Another process of the same user listens where api.sock is, while the controller's
    lock names this process: the token is not sent."""
    with (
        acquire_controller_lock(cell),
        impostor(cell) as caught,
        pytest.raises(AccessDenied) as refused,
    ):
        await attach(cell)
    said = str(refused.value)
    assert f"not sent the API token to {cell / 'api.sock'}" in said
    assert "is not the cell's controller (" in said and f"pid {os.getpid()}" in said
    assert caught.read_bytes() == b""


@AS_ROOT
def test_no_token_is_sent_to_another_users_socket(tmp_path: Path) -> None:
    """The review's case: a cell directory everyone can write, another user's socket in
    place of api.sock, and root's `cellctl orders`."""
    # Where the other user can reach it (pytest's own directory is root's alone).
    top = Path(tempfile.mkdtemp(prefix="cellctl-peer-"))
    try:
        top.chmod(0o711)
        cell = top / "cell"
        shutil.copytree(EXAMPLE_CELL, cell)
        ensure_default(cell)
        impostor_refused(cell)
    finally:
        shutil.rmtree(top)


def impostor_refused(cell: Path) -> None:
    cell.chmod(0o777)
    (cell / "api.sock").unlink(missing_ok=True)
    with impostor(cell, user=NOBODY) as caught, acquire_controller_lock(cell):
        done = cellctl(cell, "orders")
    assert done.returncode == 7, done.stdout + done.stderr
    assert "runs as nobody (uid 65534), not as root (uid 0)" in done.stderr, done.stderr
    assert f"chmod go-w {cell}" in done.stderr
    token = (cell / "api-token").read_text().strip()
    assert token.encode() not in caught.read_bytes() and caught.read_bytes() == b""
