"""``cellctl opcua adduser NAME``: a user of the cell's OPC UA server (docs/opcua.md)."""

from __future__ import annotations

from pathlib import Path

import click

from cellctl.errors import UsageError
from cellctl.service.machines import load_cell_file
from cellctl.ui.common import cell_dir, console

#: The users file when cell.toml names none yet.
DEFAULT_USERS = "opcua-users.toml"
#: The fewest characters a password may have: a short one falls to guessing.
MIN_PASSWORD = 8


@click.group("opcua")
def opcua_group() -> None:
    """The cell's OPC UA server ([opcua] in cell.toml)."""


@opcua_group.command("adduser")
@click.argument("name")
@click.option(
    "--role",
    type=click.Choice(("viewer", "operator", "engineer")),
    default=None,
    help="What the user may call: viewer reads; operator submits orders, clears alarms. "
    "Default: operator for a new user; a known user keeps the role it has.",
)
@click.pass_context
def adduser(ctx: click.Context, name: str, role: str | None) -> None:
    """Add user NAME (or set a new password, and a role with --role) in the file [opcua]
    users names.

    The password (8 characters or more) is asked twice and stored as a salted scrypt hash;
    the file is made mode 0600. A running server reads it at the next login: no restart.
    """
    from cellctl.factory.opcua.users import add_user
    from cellctl.service.client import require_cell

    directory = cell_dir(ctx)
    # Refused before the password is asked: typed twice for nothing, it would be lost.
    require_cell(directory)
    table = load_cell_file(directory).get("opcua")
    named = table.get("users") if isinstance(table, dict) else None
    path = directory / (named if isinstance(named, str) and named else DEFAULT_USERS)
    if not path.parent.is_dir():
        raise UsageError(
            f"{path}: cannot write the OPC UA users there: no directory {path.parent} "
            "(make it, or name another file in cell.toml: [opcua] users)"
        )
    password = click.prompt(
        f"password for {name} ({MIN_PASSWORD} characters or more)",
        hide_input=True,
        confirmation_prompt=True,
        err=True,
    )
    if len(password) < MIN_PASSWORD:
        raise UsageError(
            f"the password is too short: it needs {MIN_PASSWORD} characters or more, it has "
            f"{len(password)} (nothing was written)"
        )
    new, kept = add_user(Path(path), name, password, role)
    done = "added" if new else "has a new password"
    console.print(f"{path}: user {name} ({kept}) {done}", markup=False)
    if not named:
        console.print(f'name it in cell.toml: [opcua] users = "{DEFAULT_USERS}"', markup=False)
