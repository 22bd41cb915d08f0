"""``cellctl dnc stop`` of a transfer that a ``cellctl dnc send|drip`` runs by hand, holding
the machine's link itself (no ``dnc serve`` on the shop): found by its lock record, checked
to be that command, and told with :data:`HAND_STOP`, which it takes as ``dnc.stop`` (the rest
of the block, then %) before it lets the link go::

    found = hand_holder(config, "mill2")           # a Holder, or None
    if found is not None and isis_hand_transfer(found):
        said = await stop_hand_transfer(config, "mill2", found)
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cellctl.errors import MachineInUse
    from cellctl.kinds.iso_cnc.dnc.config import ShopConfig
    from cellctl.link.lock import Holder

#: The signal ``cellctl dnc stop`` sends a ``dnc send|drip`` that holds the link itself.
HAND_STOP = signal.SIGUSR1
#: Seconds ``dnc stop`` waits for such a transfer to end and let go of the link.
HAND_STOP_S = 40.0


@contextlib.contextmanager
def hand_stop_signal(hand: asyncio.Event) -> Iterator[None]:
    """Set ``hand`` on :data:`HAND_STOP` while in the block; then ignore that signal for the
    rest of this process's life (a ``dnc stop`` that read our lock record just before we
    let it go must not kill a command that has done its work)."""
    loop = asyncio.get_running_loop()
    try:
        loop.add_signal_handler(HAND_STOP, hand.set)
    except (RuntimeError, ValueError):  # not the main thread (a command run in a test's worker)
        yield  # signals go to the main thread's handlers: none of ours
        return
    try:
        yield
    finally:
        loop.remove_signal_handler(HAND_STOP)
        signal.signal(HAND_STOP, signal.SIG_IGN)


def hand_holder(config: ShopConfig, name: str) -> Holder | None:
    """Who holds machine ``name``'s lock in the shop when it is a ``cellctl dnc`` command
    run by hand on this host (not ``dnc serve``); None otherwise."""
    import socket

    from cellctl.drivers.state import StateStore
    from cellctl.link.lock import holder

    found = holder(StateStore(config.root).lock_path(name))
    if found is None or found.pid <= 0 or found.host not in ("", socket.gethostname()):
        return None
    words = found.command.split()
    if words[1:2] != ["dnc"] or words[2:3] == ["serve"]:
        return None
    return found


def is_hand_transfer(found: Holder) -> bool:
    """Whether ``found`` is a ``cellctl dnc send|drip`` (it stops its transfer cleanly on
    :data:`HAND_STOP`): its lock record says so, and so does its command line where the
    system shows it (``/proc``), so a signal never reaches another program."""
    if found.command.split()[2:3] not in (["send"], ["drip"]):
        return False
    proc = Path(f"/proc/{found.pid}/cmdline")
    if not Path("/proc/self/cmdline").exists():
        return True  # no /proc here: the lock record, held by that pid now, says it
    try:
        args = proc.read_bytes().split(b"\0")
    except OSError:
        return False  # gone meanwhile, or not ours to look at
    return any(a == b"dnc" and b in (b"send", b"drip") for a, b in itertools.pairwise(args))


def in_use_here(config: ShopConfig, name: str) -> MachineInUse | None:
    """The refusal, in what works, of machine ``name`` held by another hand command of this
    shop (None when it is held by someone else: their own words say it)."""
    from cellctl.errors import MachineInUse

    found = hand_holder(config, name)
    if found is None:
        return None
    if is_hand_transfer(found):
        return MachineInUse(
            f"{name} is busy: {found} sends it a program; wait for it to end, or stop it with "
            f"`{config.command(f'stop {name}')}` (or Ctrl-C in its terminal)"
        )
    return MachineInUse(
        f"{name} is in use by {found}: wait for it to end, or end it where it runs (Ctrl-C in "
        "its terminal)"
    )


async def stop_hand_transfer(config: ShopConfig, name: str, found: Holder) -> str:
    """Stop the transfer of the ``cellctl dnc send|drip`` ``found`` that holds ``name``'s
    link itself (no server runs): :data:`HAND_STOP` to it (it ends the transfer as
    ``dnc.stop`` does, logs where it ended and exits 130), then wait (at most
    :data:`HAND_STOP_S`) until it lets the link go; what its log says of the end."""
    import os

    from cellctl.clock import current_clock
    from cellctl.drivers.state import StateStore
    from cellctl.errors import LinkTimeout
    from cellctl.kinds.iso_cnc.dnc.status import says_all_out
    from cellctl.kinds.iso_cnc.dnc.store import ShopStore
    from cellctl.link.lock import holder

    store = ShopStore(config.root)
    before = len(store.log_lines(name, 10**9))
    lock = StateStore(config.root).lock_path(name)
    with contextlib.suppress(ProcessLookupError):  # it ended meanwhile: its log says how
        os.kill(found.pid, HAND_STOP)

    def told() -> list[str]:
        return [line.split(" ", 1)[-1] for line in store.log_lines(name, 10**9)[before:]]

    try:
        async with current_clock().timeout(HAND_STOP_S):
            while holder(lock) == found:
                said = told()
                if any(says_all_out(line) for line in said):
                    # All of it was out: the transfer runs on to its own end, unchanged.
                    return f"{name}: " + "; ".join(said)
                await current_clock().sleep(0.1)
    except TimeoutError:
        raise LinkTimeout(
            f"{name}: {found} did not end its transfer within {HAND_STOP_S:g} s of the stop: "
            "press Ctrl-C in its terminal, or reset the control"
        ) from None
    return "; ".join(told()) or f"{name}: {found} has ended (its log says nothing more)"
