"""``cellctl opcua adduser NAME`` refuses a password shorter than 8 characters, in words and
before the users file is made or changed, and says the minimum where the password is asked;
through the real command line."""

from __future__ import annotations

from pathlib import Path

from cellctl.factory.opcua.users import load_entries
from tests.test_newcomer_refusals import cellctl, copy_cell, refused

GOOD = "correct horse"


def adduser(cell: Path, name: str, password: str) -> str:
    """``cellctl opcua adduser NAME`` with ``password`` typed twice: what it said (exit 0)."""
    done = cellctl("--cell", str(cell), "opcua", "adduser", name, stdin=f"{password}\n{password}\n")
    assert done.exit_code == 0, (done.stdout, done.stderr)
    return done.stdout + done.stderr


def test_a_short_password_is_refused_before_the_users_file_is_made(tmp_path: Path) -> None:
    cell = copy_cell(tmp_path)
    said = refused(
        cellctl("--cell", str(cell), "opcua", "adduser", "carl", stdin="seven77\nseven77\n")
    )
    assert said.startswith("password for carl (8 characters or more): "), said
    assert "the password is too short: it needs 8 characters or more, it has 7" in said
    assert "nothing was written" in said and "seven77" not in said  # never shown
    assert not (cell / "opcua-users.toml").exists()


def test_a_short_new_password_leaves_the_users_file_as_it_was(tmp_path: Path) -> None:
    cell = copy_cell(tmp_path)
    adduser(cell, "alice", GOOD)
    users = cell / "opcua-users.toml"
    before = users.read_bytes()
    said = refused(cellctl("--cell", str(cell), "opcua", "adduser", "alice", stdin="x\nx\n"))
    assert "it needs 8 characters or more, it has 1" in said, said
    assert users.read_bytes() == before
    # Nobody new either.
    refused(cellctl("--cell", str(cell), "opcua", "adduser", "bob", stdin="1234567\n1234567\n"))
    assert users.read_bytes() == before and set(load_entries(users)) == {"alice"}


def test_eight_characters_are_enough_and_the_help_says_the_minimum(tmp_path: Path) -> None:
    cell = copy_cell(tmp_path)
    said = adduser(cell, "dora", "12345678")
    assert "user dora (operator) added" in said, said
    assert set(load_entries(cell / "opcua-users.toml")) == {"dora"}
    helped = cellctl("opcua", "adduser", "--help")
    assert helped.exit_code == 0 and "8 characters or more" in helped.stdout, helped.stdout
