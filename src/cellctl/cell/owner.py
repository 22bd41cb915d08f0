"""One controller per cell: the lock ``cellctl run`` holds on ``<cell>/state/controller.lock``.

``run_controller`` takes it before it reads or writes anything of the cell, so a second
controller is refused without touching the journal; the CLI asks :func:`controller_holder`
whether a controller runs (then it goes through the controller's API)::

    with acquire_controller_lock(Path("cell")):
        ...                                   # MachineInUse: "the cell in cell is already run
                                              # by cellctl run (pid 4242) since 14:15: ..."
"""

from __future__ import annotations

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
