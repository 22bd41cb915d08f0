"""A cell directory the user may not write: a machine command says whose it is and what to do.

``cellctl robot NAME status`` takes the machine's lock in ``<cell>/state/``; run by a user
other than the cell's owner (the service's user, root), it said "cannot create cell/state for
a lock: Permission denied" and left the engineer to guess. Run here as ``nobody`` on a cell
root owns, as an engineer in their own login would be beside the cell's service.
"""

from __future__ import annotations

import os
import pwd
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from .conftest import CELLCTL

#: Seconds a refused command may take (Python's start, the kinds).
REFUSED_S = 60.0

CELL_TOML = """\
[machines.robot]
kind = "ibm7545"
link = "/dev/ttyUSB0"
"""


@pytest.fixture
def bench() -> Iterator[tuple[pwd.struct_passwd, Path]]:
    """``nobody``, and a directory under /tmp (pytest's own is the test user's alone) holding
    a cell root owns and nobody can read, and nobody's home."""
    if os.geteuid() != 0:
        pytest.skip("needs root: a cell directory of another user's, run as nobody")
    user = pwd.getpwnam("nobody")
    top = Path(tempfile.mkdtemp(prefix="cellctl-bench-"))
    top.chmod(0o755)
    try:
        yield user, top
    finally:
        shutil.rmtree(top, ignore_errors=True)


@pytest.mark.parametrize("state", ["missing", "read-only"])
def test_a_cell_of_another_user_says_whose_it_is(
    bench: tuple[pwd.struct_passwd, Path], state: str
) -> None:
    user, top = bench
    cell = top / "cell"
    cell.mkdir(mode=0o755)
    (cell / "cell.toml").write_text(CELL_TOML)
    (cell / "cell.toml").chmod(0o644)
    refused = cell
    if state == "read-only":
        refused = cell / "state"
        refused.mkdir(mode=0o755)
    home = top / "home"
    home.mkdir()
    os.chown(home, user.pw_uid, user.pw_gid)
    env = {**os.environ, "HOME": str(home), "CELLCTL_RUNTIME_DIR": str(home / "run")}
    done = subprocess.run(
        [*CELLCTL, "--cell", str(cell), "robot", "robot", "status"],
        user=user.pw_uid,
        group=user.pw_gid,
        extra_groups=[],
        cwd=home,
        env=env,
        capture_output=True,
        text=True,
        timeout=REFUSED_S,
    )
    assert done.returncode == 2, done.stderr
    assert "Permission denied" in done.stderr
    assert f"{refused} belongs to root: run cellctl as root" in done.stderr


def test_an_order_posted_to_a_cell_of_another_user_says_whose_it_is(
    bench: tuple[pwd.struct_passwd, Path],
) -> None:
    """``cellctl submit`` opens the cell's journal and mailbox: it ended in a traceback
    (PermissionError) where the cell is another user's."""
    user, top = bench
    cell = top / "cell"
    shutil.copytree(Path(__file__).resolve().parent.parent / "examples" / "cell", cell)
    for path in [cell, *cell.rglob("*")]:
        path.chmod(0o755 if path.is_dir() else 0o644)
    home = top / "home"
    home.mkdir()
    os.chown(home, user.pw_uid, user.pw_gid)
    env = {**os.environ, "HOME": str(home), "CELLCTL_RUNTIME_DIR": str(home / "run")}
    done = subprocess.run(
        [*CELLCTL, "--cell", str(cell), "submit", "wax-robot-base"],
        user=user.pw_uid, group=user.pw_gid, extra_groups=[], cwd=home, env=env,
        capture_output=True, text=True, timeout=REFUSED_S,
    )  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert f"{cell} belongs to root: run cellctl as root" in done.stderr, done.stderr
    assert not list(cell.glob("*.sqlite3"))  # nothing made
