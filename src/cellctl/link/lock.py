"""One owner per machine: an exclusive lock on a file, with the holder written in it.

A driver takes the lock of its machine before it opens the link, so a second process (or a
second driver in the same process) is refused before it sends a byte::

    with OwnerLock.acquire(Path("cell/state/machine-cnc1.lock"), "cnc1"):
        ...                       # MachineInUse if another owner holds it:
                                  # "cnc1 is in use by cellctl run (pid 4242) since 14:15: ..."
    holder(Path("cell/state/machine-cnc1.lock"))   # Holder(...) or None when free

The lock is ``flock(LOCK_EX | LOCK_NB)`` on the file: the kernel drops it when its owner exits
however it exits (kill -9 included), so a lock file left behind never blocks anyone; the next
owner takes it and rewrites the holder record (JSON: pid, command, since, host). flock locks
belong to an open file description, so two opens in one process conflict as two processes do.
The descriptor is close-on-exec (a child started with exec does not inherit the lock); a child
forked without exec shares it, as with any flock.

The owner deletes its lock file when it gives the lock back, while it still holds it, so
lock files do not pile up (one per link ever used). A taker checks that the file it locked is
still the one at the path, and tries again if not: a process that opened the file just before
it was deleted can never lock that orphan while another owner locks the new file of the same
name.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import stat
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Self

from cellctl.clock import REAL_CLOCK
from cellctl.errors import MachineInUse, UsageError
from cellctl.files import rights_advice

#: What a refusal says; ``{what}`` is the machine, ``{holder}`` the holder (see Holder.__str__),
#: ``{advice}`` what to do about it (:func:`advice`).
IN_USE = "{what} is in use by {holder}: {advice}"
#: Holders that serve the control API (their own words: see default_process_label).
API_HOLDERS = ("cellctl run", "cellctl demo", "cellctl dnc serve", "cellctl emulate factory")


def advice(holder: Holder | str) -> str:
    """What a refused opener can do: ask a holder that serves the API through it, use the
    console that holds it, or wait for a one-off command (it serves nothing to ask)."""
    command = holder.command if isinstance(holder, Holder) else ""
    if command.startswith(API_HOLDERS):
        return "use `cellctl console` or the API"
    if command.startswith("cellctl console"):
        return "use that console, or close it"
    return "wait for it to end, or end it where it runs (Ctrl-C in its terminal)"


_label: str | None = None

#: The environment variable that names the runtime directory itself (see runtime_dir).
RUNTIME_ENV = "CELLCTL_RUNTIME_DIR"
#: The machine's lock directory (FHS /run/lock, world-writable, sticky): the same path in
#: every process, a service's included, whatever its environment.
SYSTEM_LOCK_DIR = "/run/lock"


@dataclass(frozen=True)
class Holder:
    """Who holds a lock: ``pid`` on ``host`` running ``command`` since ``since`` (unix time).

    A held lock whose record cannot be read (being written, or garbage) has ``pid`` 0.
    """

    pid: int
    command: str
    since: float
    host: str

    def __str__(self) -> str:
        if not self.pid:
            return "another process"
        clock = time.strftime("%H:%M", time.localtime(self.since))
        where = f" on {self.host}" if self.host and self.host != socket.gethostname() else ""
        return f"{self.command} (pid {self.pid}{where}) since {clock}"


def default_process_label(argv: list[str] | None = None) -> str:
    """A short label for this process from its command line: ``cellctl robot status``.

    The program's name plus at most three command words; options, their values and anything
    that looks like a path or a file are left out.
    """
    args = list(sys.argv if argv is None else argv)
    if not args:
        return "python"
    program = Path(args[0]).name
    if program in ("__main__.py", "-", "-m", "-c", ""):
        program = Path(args[0]).parent.name or "python"
    words: list[str] = []
    skip_value = False
    for word in args[1:]:
        if word.startswith("-"):
            # "--cell DIR": the next word is the option's value (unless written --cell=DIR)
            skip_value = "=" not in word and word != "--"
            continue
        if skip_value:
            skip_value = False
            continue
        if "/" in word or "." in word or ":" in word or not word.isprintable():
            continue
        words.append(word)
        if len(words) == 3:
            break
    return " ".join([program, *words])[:60]


def set_process_label(label: str | None) -> None:
    """Name this process in the lock records it writes from now on (None: from sys.argv)."""
    global _label
    _label = label


def process_label() -> str:
    """The label this process writes in its lock records."""
    return _label or default_process_label()


def _ensure_private_dir(path: Path) -> Path:
    """Create ``path`` mode 0700 if missing; refuse one that is not ours or not a directory."""
    try:
        path.mkdir(mode=0o700)
    except FileExistsError:
        pass
    except OSError as e:
        raise UsageError(f"cannot create cellctl's directory {path}: {e.strerror}") from None
    st = path.lstat()
    if not stat.S_ISDIR(st.st_mode):
        raise UsageError(f"{path} should be a directory of cellctl's, and is not one")
    if st.st_uid != os.getuid():
        raise UsageError(
            f"{path} belongs to uid {st.st_uid}, not to this user: cellctl will not keep its "
            "locks and sockets there (remove it, or set CELLCTL_RUNTIME_DIR)"
        )
    if stat.S_IMODE(st.st_mode) & 0o077:
        os.chmod(path, 0o700)
    return path


def runtime_dir() -> Path:
    """This user's private directory for locks and sockets, created mode 0700.

    The same for every process of the user whatever its environment: a login shell (with
    ``$XDG_RUNTIME_DIR``) and the cell's systemd service (without, and with a private /tmp)
    must see each other's link locks. So: ``$CELLCTL_RUNTIME_DIR`` if set (tests, unusual
    setups), else ``/run/lock/cellctl-<uid>`` (where serial-port locks live; the service unit
    may write there), else ``$XDG_RUNTIME_DIR/cellctl``, else ``/tmp/cellctl-<uid>``.

    Raises UsageError when the directory exists but belongs to someone else.
    """
    given = os.environ.get(RUNTIME_ENV)
    if given and os.path.isabs(given):
        return _ensure_private_dir(Path(given))
    if os.path.isdir(SYSTEM_LOCK_DIR) and os.access(SYSTEM_LOCK_DIR, os.W_OK | os.X_OK):
        return _ensure_private_dir(Path(SYSTEM_LOCK_DIR) / f"cellctl-{os.getuid()}")
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    if xdg and os.path.isabs(xdg) and os.path.isdir(xdg):
        return _ensure_private_dir(Path(xdg) / "cellctl")
    return _ensure_private_dir(Path("/tmp") / f"cellctl-{os.getuid()}")


def _parse_record(data: bytes) -> Holder | None:
    try:
        # raw_decode: a record being rewritten may still carry the old record's tail.
        record, _ = json.JSONDecoder().raw_decode(data.decode("utf-8"))
        return Holder(
            pid=int(record["pid"]),
            command=str(record["command"]),
            since=float(record["since"]),
            host=str(record["host"]),
        )
    except (ValueError, KeyError, TypeError, AttributeError):
        return None


def _read_record(fd: int) -> Holder:
    """The record of a lock that is held; retried briefly, as its owner may be writing it."""
    for attempt in range(3):
        found = _parse_record(os.pread(fd, 4096, 0))
        if found is not None:
            return found
        if attempt < 2:
            time.sleep(0.01)
    return Holder(pid=0, command="", since=0.0, host="")


def _open(path: Path, flags: int) -> int:
    try:
        return os.open(path, flags | os.O_CLOEXEC | os.O_NOFOLLOW, 0o600)
    except FileNotFoundError:
        raise
    except OSError as e:
        raise UsageError(
            f"cannot open the lock file {path}: {e.strerror}{rights_advice(path, e)}"
        ) from None


def _same_file(fd: int, path: Path) -> bool:
    """True if ``path`` is (still) the file open as ``fd``."""
    try:
        there = os.stat(path, follow_symlinks=False)
    except FileNotFoundError:
        return False
    mine = os.fstat(fd)
    return (there.st_dev, there.st_ino) == (mine.st_dev, mine.st_ino)


def _lock_the_file_at(path: Path, what: str, refusal: str) -> int:
    """Open and lock the file at ``path`` (created if missing): its descriptor, the lock
    held. MachineInUse if another owner holds it. A file deleted (its owner gave it back)
    between our open and our lock is not the lock any more: open again."""
    for _ in range(100):  # each turn means another owner came and went meanwhile
        fd = _open(path, os.O_RDWR | os.O_CREAT)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            found = _read_record(fd)
            os.close(fd)
            raise MachineInUse(
                refusal.format(what=what, holder=found, advice=advice(found))
            ) from None
        except BaseException:
            os.close(fd)
            raise
        if _same_file(fd, path):
            return fd
        os.close(fd)
    raise MachineInUse(
        refusal.format(what=what, holder="another process", advice=advice("another process"))
    )


def holder(path: Path | str) -> Holder | None:
    """Who holds the lock ``path`` now; None when nobody does (or the file does not exist)."""
    try:
        fd = _open(Path(path), os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return _read_record(fd)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def refuse_if_held(path: Path | str, what: str, *, refusal: str = IN_USE) -> None:
    """MachineInUse, as :meth:`OwnerLock.acquire` would say it, if another owner holds the
    lock ``path`` now: a look before starting what would take it later (not a lock)."""
    found = holder(path)
    if found is not None:
        raise MachineInUse(refusal.format(what=what, holder=found, advice=advice(found)))


class OwnerLock:
    """An exclusive owner lock on a file; see the module docstring.

    Take it with :meth:`acquire`; give it back with :meth:`release` or by leaving a ``with``.
    """

    def __init__(self, path: Path, fd: int, what: str) -> None:
        self.path = path
        self.what = what
        self._fd = fd

    @classmethod
    def acquire(cls, path: Path | str, what: str, *, refusal: str = IN_USE) -> OwnerLock:
        """Take the lock ``path`` for ``what`` (a machine, a link, a cell) without waiting.

        Raises MachineInUse, its message ``refusal`` formatted with ``what`` and the holder,
        when another owner holds it (another process, or another open in this one).
        """
        path = Path(path)
        if not path.parent.is_dir():
            try:
                path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            except OSError as e:
                raise UsageError(
                    f"cannot create {path.parent} for a lock: {e.strerror}"
                    f"{rights_advice(path.parent, e)}"
                ) from None
        fd = _lock_the_file_at(path, what, refusal)
        try:
            if stat.S_IMODE(os.fstat(fd).st_mode) & 0o077:
                with contextlib.suppress(PermissionError):
                    os.fchmod(fd, 0o600)
            record = json.dumps(
                {
                    "pid": os.getpid(),
                    "command": process_label(),
                    "since": REAL_CLOCK.now(),  # other processes read it: wall time
                    "host": socket.gethostname(),
                }
            ).encode()
            # Write, then cut what is left of an older (longer) record: a reader parses the
            # first JSON value, so it never sees an empty file while we hold the lock.
            os.pwrite(fd, record + b"\n", 0)
            os.ftruncate(fd, len(record) + 1)
        except BaseException:
            os.close(fd)
            raise
        return cls(path, fd, what)

    @property
    def held(self) -> bool:
        """True until released."""
        return self._fd >= 0

    def release(self) -> None:
        """Give the lock back (once; later calls do nothing)."""
        fd, self._fd = self._fd, -1
        if fd < 0:
            return
        try:
            # Clear the record and delete the file while still holding the lock: a stale
            # record never lingers, and a taker that locked this file finds it gone.
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
            with contextlib.suppress(OSError):
                if _same_file(fd, self.path):
                    os.unlink(self.path)
        finally:
            os.close(fd)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.release()

    def __del__(self) -> None:
        # A lock dropped without release (an error path that forgot it) must not stay held
        # for the rest of a long-running process.
        if getattr(self, "_fd", -1) >= 0:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = -1

    def __repr__(self) -> str:
        state = "held" if self.held else "released"
        return f"<OwnerLock {self.path} ({self.what}, {state})>"


__all__ = [
    "IN_USE",
    "RUNTIME_ENV",
    "SYSTEM_LOCK_DIR",
    "Holder",
    "OwnerLock",
    "default_process_label",
    "holder",
    "process_label",
    "runtime_dir",
    "set_process_label",
]
