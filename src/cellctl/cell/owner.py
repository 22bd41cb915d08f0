"""One controller per cell: the lock ``cellctl run`` holds on ``<cell>/state/controller.lock``.

``run_controller`` takes it before it reads or writes anything of the cell, so a second
controller is refused without touching the journal; the CLI asks :func:`controller_holder`
whether a controller runs (then it goes through the controller's API)::

    with acquire_controller_lock(Path("cell")):
        ...                                   # MachineInUse: "the cell in cell is already run
                                              # by cellctl run (pid 4242) since 14:15: ..."
"""

from __future__ import annotations

import grp
import os
import pwd
import stat
from pathlib import Path
from typing import TYPE_CHECKING

from cellctl.errors import UsageError
from cellctl.link.lock import Holder, OwnerLock, holder

if TYPE_CHECKING:
    from cellctl.cell.config import CellConfig

#: What a second controller is told; ``{what}`` is the cell directory.
ALREADY_RUN = "the cell in {what} is already run by {holder}: use `cellctl console` or the API"


def controller_lock_path(cell_dir: Path | str) -> Path:
    """The controller lock of the cell in ``cell_dir``."""
    return Path(cell_dir) / "state" / "controller.lock"


def acquire_controller_lock(cell_dir: Path | str) -> OwnerLock:
    """Take the cell's controller lock (MachineInUse, naming the holder, if one runs).

    Refuses (UsageError) a directory that does not exist rather than create it.
    """
    if not Path(cell_dir).is_dir():
        raise UsageError(f"{cell_dir}: no such cell directory")
    return OwnerLock.acquire(controller_lock_path(cell_dir), str(cell_dir), refusal=ALREADY_RUN)


def _name(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return f"uid {uid}"


def _private_group(gid: int, owner: int) -> bool:
    """Whether group ``gid`` holds the owner alone (a user private group, as umask 002
    setups make every directory group-writable with): no other member, no other user's
    primary group."""
    try:
        members = set(grp.getgrgid(gid).gr_mem)
        if pwd.getpwuid(owner).pw_gid != gid:
            return False  # not the owner's own group
    except KeyError:
        return False
    mine = {_name(owner)}
    return members <= mine and all(u.pw_uid == owner for u in pwd.getpwall() if u.pw_gid == gid)


def refuse_shared_directory(cell_dir: Path | str) -> None:
    """UsageError, saying why and what to do, unless the cell directory is its runner's
    alone: owned by the user running the controller, and writable by nobody else (its group
    only if that group is the owner's own). Whoever can write it can replace every file the
    controller trusts there: put a socket of their own in place of ``api.sock`` and be sent
    the engineer's token by the next command, or a link in place of the journal."""
    directory = Path(cell_dir)
    info = directory.stat()  # the directory itself, through a link to it
    me = os.geteuid()
    if info.st_uid != me:
        raise UsageError(
            f"{directory} belongs to {_name(info.st_uid)}, not to {_name(me)} who runs "
            f"`cellctl run`: run it as {_name(info.st_uid)} (a controller writes its token, "
            "journal and socket there, for the directory's owner to read)"
        )
    others = info.st_mode & stat.S_IWOTH
    group = info.st_mode & stat.S_IWGRP and not _private_group(info.st_gid, info.st_uid)
    if others or group:
        who = "every user" if others else f"the group {_group(info.st_gid)}"
        raise UsageError(
            f"{directory} can be written by {who} (mode {stat.S_IMODE(info.st_mode):04o}): "
            "anyone who can write it can put their own socket in place of api.sock and be "
            "sent the API token, or a link in place of the journal; make it yours alone "
            f"(`chmod go-w {directory}`) and start `cellctl run` again"
        )


def _group(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return f"gid {gid}"


def controller_holder(cell_dir: Path | str) -> Holder | None:
    """The running controller of the cell in ``cell_dir``, or None when none runs."""
    return holder(controller_lock_path(cell_dir))


def refuse_if_machines_held(config: CellConfig) -> None:
    """MachineInUse, naming the holder, if another process holds a machine's or the PLC's
    link now (a console standalone, a ``cellctl robot`` session): the controller says so
    before it serves its API or opens a link, not after it has started."""
    # Here, not at the top: the commands that only ask controller_holder() stay light.
    from cellctl.drivers.base import refuse_if_link_held
    from cellctl.drivers.state import StateStore
    from cellctl.protocol.plc import PlcMap

    store = StateStore(config.directory)
    for machine in [config.robot, *config.mills]:
        refuse_if_link_held(machine.link, machine.name, store)
    refuse_if_link_held(PlcMap.from_toml(config.plc).url, "plc", store)
