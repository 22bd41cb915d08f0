"""The journal and the mailbox (SQLite files in the cell directory) are never opened through a
symbolic link, nor are their side files (-wal, -shm, -journal): a link is refused in words,
naming it, before anything is opened or changed; what it points to stays as it was. A file
that is not a database is said so, not shown as a traceback. The side files are 0600."""

from __future__ import annotations

import os
import shutil
import sqlite3
import stat
import subprocess
from pathlib import Path

import pytest

from cellctl.cell.journal import JOURNAL_FILE, open_journal
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.errors import UsageError
from cellctl.mailbox import MAILBOX_FILE
from cellctl.plan.snapshot import copy_store
from tests.conftest import CELLCTL

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    return directory


@pytest.fixture
def victim(tmp_path: Path) -> Path:
    """A file of someone else's the link points to: world-readable text."""
    path = tmp_path / "elsewhere" / "passwd"
    path.parent.mkdir()
    path.write_text("root:x:0:0:root:/root:/bin/bash\n")
    path.chmod(0o644)
    return path


def cellctl(cell: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, "--cell", str(cell), *args],
        capture_output=True,
        text=True,
        timeout=90,
        stdin=subprocess.DEVNULL,
    )


def unchanged(victim: Path) -> None:
    assert stat.S_IMODE(victim.stat().st_mode) == 0o644
    assert victim.read_text() == "root:x:0:0:root:/root:/bin/bash\n"
    assert sorted(p.name for p in victim.parent.iterdir()) == ["passwd"]


@pytest.mark.parametrize(
    ("name", "command"),
    [
        (JOURNAL_FILE, ["run"]),
        (MAILBOX_FILE, ["orders"]),
        (JOURNAL_FILE + "-wal", ["run"]),
        (MAILBOX_FILE + "-shm", ["orders"]),
        (MAILBOX_FILE + "-journal", ["submit", "wax-robot-base"]),
    ],
)
def test_a_link_in_place_of_a_database_or_its_side_file_is_refused_untouched(
    cell: Path, victim: Path, name: str, command: list[str]
) -> None:
    if name.endswith(("-wal", "-shm", "-journal")):
        # The database itself is there: only its side file is a link.
        base = name.rsplit("-", 1)[0]
        if base == JOURNAL_FILE:
            open_journal(cell).close()
        else:
            assert cellctl(cell, "submit", "wax-robot-base").returncode == 0
    (cell / name).symlink_to(victim)
    done = cellctl(cell, *command)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert (
        f"{cell / name} is a symbolic link: cellctl never opens its journal or mailbox "
        "through one; remove the link" in done.stderr
    ), done.stderr
    unchanged(victim)
    assert (cell / name).is_symlink()


def test_a_dangling_link_makes_no_file_where_it_points(cell: Path, tmp_path: Path) -> None:
    nowhere = tmp_path / "elsewhere" / "made-by-cellctl"
    nowhere.parent.mkdir()
    (cell / MAILBOX_FILE).symlink_to(nowhere)
    (cell / JOURNAL_FILE).symlink_to(nowhere)
    for command in (["submit", "wax-robot-base"], ["run"], ["plan", "--shift", "1h"]):
        done = cellctl(cell, *command)
        assert done.returncode == 2, (command, done.stdout + done.stderr)
        assert "is a symbolic link" in done.stderr and "Traceback" not in done.stderr
    # Reads find no file there (a dangling link is none) and make none.
    for command in (["orders"], ["alarm", "list"]):
        done = cellctl(cell, *command)
        assert "Traceback" not in done.stderr, done.stderr
    assert list(nowhere.parent.iterdir()) == []


def test_the_plans_copy_of_a_store_refuses_a_link(cell: Path, victim: Path) -> None:
    (cell / MAILBOX_FILE).symlink_to(victim)
    with pytest.raises(UsageError, match="is a symbolic link"):
        copy_store(cell / MAILBOX_FILE, cell / "copy.sqlite3")
    unchanged(victim)
    assert not (cell / "copy.sqlite3").exists()


def test_a_file_that_is_no_database_is_said_in_words(cell: Path) -> None:
    (cell / JOURNAL_FILE).write_text("not a journal\n")
    done = cellctl(cell, "run")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert f"{cell / JOURNAL_FILE} is not a SQLite database" in done.stderr, done.stderr
    assert (cell / JOURNAL_FILE).read_text() == "not a journal\n"


def test_the_side_files_are_private_too(cell: Path) -> None:
    """A -wal and -shm left readable (a copy restored with a loose umask) are made 0600 when
    the journal is opened, beside a connection that keeps them there."""
    open_journal(cell).close()
    keeper = sqlite3.connect(cell / JOURNAL_FILE)
    try:
        keeper.execute("SELECT count(*) FROM sqlite_master").fetchall()
        sides = [cell / (JOURNAL_FILE + "-wal"), cell / (JOURNAL_FILE + "-shm")]
        for path in [cell / JOURNAL_FILE, *sides]:
            os.chmod(path, 0o644)
        journal = open_journal(cell)
        try:
            for path in [cell / JOURNAL_FILE, *sides]:
                assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
        finally:
            journal.close()
    finally:
        keeper.close()
