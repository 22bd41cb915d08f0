"""Reading a file a user names: a regular file only, and no more of it than a limit.

A path in cell.toml, an orders file or on the command line can name something that is not a
file: a serial device (``link = "/dev/ttyS0"`` under the wrong table), a FIFO, ``/dev/zero``.
Reading one blocks forever or never ends, so every such path is read through here::

    data = read_file(path)                        # bytes, at most MAX_FILE_BYTES
    text = read_text(path, limit=1_000_000)       # decoded (UnicodeDecodeError as bytes.decode)

What is not a regular file is refused before it is opened (a FIFO's open would block), and
again once open (it may have been swapped since); a file over ``limit`` is refused whole.
Both raise :class:`OSError` (``strerror`` says what the path is, or its size), as ``open``
does for a missing file, so a caller's ``except OSError`` reports them all alike.

A file a user names for output (a report, a drawing, a compiled program) is written through
:func:`write_output`: made or replaced, never through a symbolic link or onto what is not a
regular file (a link planted there would turn the write onto another file)::

    write_output(Path("shift.csv"), text)
"""

from __future__ import annotations

import errno
import os
import pwd
import stat
from pathlib import Path

#: The most read of a file by default (the largest program a host sends is far smaller).
MAX_FILE_BYTES = 64 * 1024 * 1024

# What a path is, in the user's words, by its file type.
_TYPES = {
    stat.S_IFDIR: "a directory",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFIFO: "a FIFO",
    stat.S_IFSOCK: "a socket",
}


def _regular(mode: int, path: Path) -> None:
    if not stat.S_ISREG(mode):
        what = _TYPES.get(stat.S_IFMT(mode), "not a file")
        raise OSError(errno.EINVAL, f"{what}, not a regular file", str(path))


def _too_large(limit: int, path: Path) -> OSError:
    return OSError(errno.EFBIG, f"more than {limit} bytes (refused whole)", str(path))


def read_file(path: Path | str, *, limit: int = MAX_FILE_BYTES) -> bytes:
    """The whole of the regular file ``path``; OSError if it is something else or too large."""
    path = Path(path)
    _regular(os.stat(path).st_mode, path)
    # O_NONBLOCK: a FIFO put in its place since the stat must not block the open.
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | getattr(os, "O_CLOEXEC", 0))
    with os.fdopen(fd, "rb") as f:
        found = os.fstat(fd)
        _regular(found.st_mode, path)
        if found.st_size > limit:
            raise _too_large(limit, path)
        data = f.read(limit + 1)
    if len(data) > limit:  # it grew since
        raise _too_large(limit, path)
    return data


def reason(error: OSError | UnicodeDecodeError) -> str:
    """Why a read failed, in a user's words (not Python's ``[Errno 22] ...: 'path'``)."""
    if isinstance(error, UnicodeDecodeError):
        return f"byte {error.start + 1} is not {error.encoding} text"
    return error.strerror or str(error)


def read_text(
    path: Path | str,
    encoding: str = "utf-8",
    errors: str = "strict",
    *,
    limit: int = MAX_FILE_BYTES,
) -> str:
    """:func:`read_file` decoded (``UnicodeDecodeError`` as :meth:`bytes.decode` raises it)."""
    return read_file(path, limit=limit).decode(encoding, errors)


def write_output(path: Path | str, data: str | bytes, *, encoding: str = "utf-8") -> None:
    """Write ``data`` to the output file ``path`` (made, or replaced if it is a regular
    file). A symbolic link or anything not a regular file there is refused (OSError, its
    ``strerror`` in the user's words), and the open does not follow a link swapped in since."""
    path = Path(path)
    try:
        mode = path.lstat().st_mode
    except FileNotFoundError:
        pass
    else:
        if stat.S_ISLNK(mode):
            raise OSError(
                errno.ELOOP,
                "a symbolic link: name the file itself (no output goes through one)",
                str(path),
            )
        _regular(mode, path)
    raw = data.encode(encoding) if isinstance(data, str) else data
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666)
    with os.fdopen(fd, "wb") as f:
        f.write(raw)


def rights_advice(path: Path, error: OSError) -> str:
    """For a file of the cell's refused for want of rights (a lock, a database): whose
    directory it is, and what to do (run as its owner, as the cell's service does), as
    ``": /cell belongs to root: run cellctl as root, ..."``; "" for any other failure."""
    if error.errno not in (errno.EACCES, errno.EPERM):
        return ""
    there = path.parent
    while not there.exists() and there != there.parent:
        there = there.parent
    try:
        uid = there.stat().st_uid
        owner = pwd.getpwuid(uid).pw_name
    except (KeyError, OSError):
        return ": this user may not write there"
    if uid == os.geteuid():
        return f": {there} is read-only: let its owner write there (chmod u+w)"
    return f": {there} belongs to {owner}: run cellctl as {owner}, or let this user write there"
