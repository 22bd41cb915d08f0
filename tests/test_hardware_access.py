"""A serial port the user may not open: the refusal says what to do, in the group's name.

On a fresh bench the USB adapter's node is ``crw-rw---- root dialout`` and the engineer is not
in ``dialout``: "permission denied" alone sends them searching. The command is run as a user
outside the device's group (``nobody``), on a pty given the owner, group and mode such a node
has, with nothing else in its way.
"""

from __future__ import annotations

import grp
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


@pytest.fixture
def outsider() -> Iterator[tuple[int, int, Path]]:
    """The uid and gid of ``nobody`` and a home of its own (under /tmp: pytest's own directory
    is the test user's alone)."""
    if os.geteuid() != 0:
        pytest.skip("needs root: only root can give a device to a group the user is not in")
    user = pwd.getpwnam("nobody")
    home = Path(tempfile.mkdtemp(prefix="cellctl-outsider-"))
    os.chown(home, user.pw_uid, user.pw_gid)
    try:
        yield user.pw_uid, user.pw_gid, home
    finally:
        shutil.rmtree(home, ignore_errors=True)


def _device_group() -> grp.struct_group:
    """Debian's group of serial ports, else the first group ``nobody`` is not in."""
    try:
        return grp.getgrnam("dialout")
    except KeyError:
        return next(g for g in grp.getgrall() if "nobody" not in g.gr_mem and g.gr_gid != 65534)


def test_a_port_of_a_group_the_user_is_not_in_says_to_join_it(
    outsider: tuple[int, int, Path],
) -> None:
    uid, gid, home = outsider
    group = _device_group()
    master, slave = os.openpty()
    path = os.ttyname(slave)
    try:
        os.chown(path, 0, group.gr_gid)
        os.chmod(path, 0o660)
        env = {
            **os.environ,
            "HOME": str(home),
            "CELLCTL_RUNTIME_DIR": str(home / "run"),
            "XDG_RUNTIME_DIR": str(home),
        }
        done = subprocess.run(
            [*CELLCTL, "robot", "--link", path, "status"],
            user=uid,
            group=gid,
            extra_groups=[],
            cwd=home,
            env=env,
            capture_output=True,
            text=True,
            timeout=REFUSED_S,
        )
    finally:
        os.close(slave)
        os.close(master)
    assert done.returncode == 3, done.stderr
    assert f"cannot open serial port {path}: permission denied" in done.stderr
    assert f"add yourself to its group {group.gr_name}" in done.stderr
    assert f"usermod -aG {group.gr_name} nobody" in done.stderr
    assert "log in again" in done.stderr
