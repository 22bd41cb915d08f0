"""SQLite files shared by the controller and the CLI: the journal and the SQLite mailbox.

:class:`SqliteStore` opens a file in WAL mode with ``synchronous=FULL`` (every commit is on
disk before the call returns, so a kill -9 loses nothing that returned) and gives its
subclasses one-transaction helpers::

    class Notes(SqliteStore):
        def add(self, text: str) -> None:
            with self._write() as db:                     # BEGIN IMMEDIATE ... COMMIT
                db.execute("INSERT INTO notes (text) VALUES (?)", (text,))

Writers take the write lock up front (``BEGIN IMMEDIATE``) so a read-modify-write cannot
interleave with another process, and wait up to ``busy_timeout`` seconds for it rather than
failing with "database is locked".

A store may keep in-memory views of what it reads often (:meth:`SqliteStore._views_current`):
its own writes update them after they commit (:meth:`SqliteStore._after_commit`), and a
commit by any other connection (the CLI, another process) is seen through SQLite's
``PRAGMA data_version`` and makes them be read again from the file. The file stays the
truth: a view only ever answers what a read of the file would have answered.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import stat
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import TracebackType
from typing import Any, Self

from cellctl.errors import UsageError
from cellctl.files import rights_advice

#: Seconds a writer waits for another process's write lock before giving up.
BUSY_TIMEOUT = 30.0


#: The files SQLite keeps beside a database, named after it: each is opened by name.
SIDE_FILES = ("-wal", "-shm", "-journal")
#: SQLite's result codes for a file that is not a database, or a damaged one.
_NOT_A_DATABASE = (26, 11)  # SQLITE_NOTADB, SQLITE_CORRUPT


def _files(path: Path) -> list[Path]:
    return [path, *(path.with_name(path.name + side) for side in SIDE_FILES)]


def _link(file: Path) -> UsageError:
    return UsageError(
        f"{file} is a symbolic link: cellctl never opens its journal or mailbox through "
        "one; remove the link (and put the file itself there)"
    )


def refuse_links(path: Path) -> None:
    """UsageError, naming the file, when ``path`` or one of its side files is a symbolic link
    or not a plain file: SQLite opens them by name, so a link would have the journal (or the
    mailbox) written into, and made private, whatever file it points to."""
    for file in _files(path):
        try:
            mode = file.lstat().st_mode
        except FileNotFoundError:
            continue
        if stat.S_ISLNK(mode):
            raise _link(file)
        if not stat.S_ISREG(mode):
            raise UsageError(f"{file} is not a plain file; remove it")


def make_private(path: Path) -> None:
    """Create ``path`` mode 0600 if missing, and tighten it and its side files (-wal, -shm,
    -journal) if looser; UsageError for a link in their place (:func:`refuse_links`).

    SQLite gives the side files it creates the database file's permissions, so a private
    database keeps its journal private too.

    An existing file is never opened for reading or writing here: closing any descriptor
    of a file drops every POSIX lock this process holds on it, so opening and closing the
    database beside a connection already open in this process would take that connection's
    locks away. Another process would then see no reader, checkpoint on close and delete the
    -wal and -shm files, and this process's writes would go on into the deleted WAL, where
    nobody else ever reads them. The chmod does not follow links (``fchmodat`` with
    ``AT_SYMLINK_NOFOLLOW``, which works through an ``O_PATH`` descriptor, whose closing
    drops no lock).
    """
    refuse_links(path)
    try:
        # O_EXCL: a link (even a dangling one) put here since the check is not followed.
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
    except FileExistsError:
        pass  # there already: no descriptor of it opened, none closed
    else:
        os.close(fd)  # a new file: nothing of this process holds a lock on it yet
    for file in _files(path):
        with contextlib.suppress(FileNotFoundError, PermissionError):
            if file.lstat().st_mode & 0o077:
                try:
                    os.chmod(file, 0o600, follow_symlinks=False)
                except NotImplementedError:
                    # Linux says so for a link (swapped in since the check): never followed.
                    raise _link(file) from None


def connect(
    path: Path, schema: str, busy_timeout: float = BUSY_TIMEOUT, *, durable: bool = True
) -> sqlite3.Connection:
    """Open ``path`` (private: 0600) in WAL mode, autocommit, ``synchronous=FULL``, and create
    ``schema``. ``durable=False``: ``synchronous=OFF``, no commit waits for the disk, for a
    throwaway copy (a plan's) that nothing reads after a crash."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        make_private(path)
    except PermissionError as e:
        # The cell's directory is another user's (or read-only): said, with what to do.
        raise UsageError(f"cannot open {path}: {e.strerror}{rights_advice(path, e)}") from None
    # isolation_level=None: no implicit transactions; each method says BEGIN itself.
    conn = sqlite3.connect(
        path, timeout=busy_timeout, isolation_level=None, check_same_thread=False
    )
    try:
        _prepare(conn, schema, busy_timeout, durable)
    except sqlite3.DatabaseError as e:
        conn.close()
        if getattr(e, "sqlite_errorcode", None) in _NOT_A_DATABASE:
            raise not_a_database(path, e) from None
        raise
    except BaseException:
        conn.close()
        raise
    make_private(path)  # the -wal and -shm WAL mode has just made
    return conn


def not_a_database(path: Path, error: sqlite3.DatabaseError) -> UsageError:
    """The words for a file SQLite cannot read as a database."""
    return UsageError(
        f"{path} is not a SQLite database, or a damaged one ({error}): cellctl keeps its "
        "journal or mailbox there; move that file away (a new one is made) or put back a copy"
    )


def _prepare(conn: sqlite3.Connection, schema: str, busy_timeout: float, durable: bool) -> None:
    conn.row_factory = sqlite3.Row
    conn.execute(f"PRAGMA busy_timeout = {int(busy_timeout * 1000)}")
    conn.execute("PRAGMA journal_mode = WAL")
    # FULL: in WAL mode NORMAL may lose the last commits on power loss; FULL syncs each one.
    conn.execute(f"PRAGMA synchronous = {'FULL' if durable else 'OFF'}")
    conn.execute("BEGIN IMMEDIATE")
    try:
        for statement in schema.split(";"):
            if statement.strip():
                conn.execute(statement)
        conn.execute("COMMIT")
    except BaseException:
        conn.execute("ROLLBACK")
        raise


class SqliteStore:
    """One SQLite file with a schema; use as a context manager or call :meth:`close`.

    ``durable=False`` only for a throwaway copy (see :func:`connect`)."""

    def __init__(self, path: Path, schema: str, *, durable: bool = True) -> None:
        self.path = Path(path)
        self._conn = connect(self.path, schema, durable=durable)
        # One connection, possibly used from worker threads: one transaction at a time.
        self._lock = threading.Lock()
        self._probe = self._conn.cursor()  # for PRAGMA data_version, asked every round
        # Commits of this connection, and the data_version the in-memory views were read
        # at (None: no views, or they must be read again).
        self._writes = 0
        self._views_at: int | None = None
        self._staged: list[Callable[[], None]] = []

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                yield self._conn
            except BaseException:
                self._staged.clear()
                self._conn.execute("ROLLBACK")
                raise
            try:
                self._conn.execute("COMMIT")
            except BaseException:
                # Whether it is on disk is unknown: the views are read again from the file.
                self._staged.clear()
                self._views_at = None
                raise
            self._writes += 1
            staged, self._staged = self._staged, []
            for apply in staged:
                apply()

    def _after_commit(self, apply: Callable[[], None]) -> None:
        """Inside :meth:`_write`: update the views with ``apply`` once the transaction has
        committed (never, if it rolls back). Without views loaded, nothing to update."""
        if self._views_at is not None:
            self._staged.append(apply)

    def _read(self, sql: str, args: Iterable[Any] = ()) -> list[sqlite3.Row]:
        with self._lock:
            return self._conn.execute(sql, tuple(args)).fetchall()

    def _data_version(self) -> int:
        # Changes whenever another connection committed; never for this one's commits.
        return int(self._probe.execute("PRAGMA data_version").fetchone()[0])

    def _views_current(self) -> None:
        """Hold ``self._lock`` when calling: make the views match the file, reading them
        again (:meth:`_load_views`) if they were never read or another connection committed
        since."""
        seen = self._data_version()
        if seen != self._views_at:
            # The version is read first: a commit landing during the load is seen next time.
            self._load_views(self._conn)
            self._views_at = seen

    def _load_views(self, db: sqlite3.Connection) -> None:
        """Read the in-memory views from the file (a subclass that keeps views says how)."""

    @property
    def version(self) -> tuple[int, int]:
        """Changes whenever anything in the file may have changed (a commit by this store or
        by any other connection): what is worked out from the file's contents and kept
        needs working out again only when this differs from when it was."""
        with self._lock:
            return (self._data_version(), self._writes)

    def close(self) -> None:
        """Close the file; the store is unusable afterwards."""
        with self._lock:
            self._conn.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
