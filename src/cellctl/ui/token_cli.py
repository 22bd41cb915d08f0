"""``cellctl token add|list|revoke`` (the API's tokens with their roles) and ``cellctl audit``
(who did what): see docs/api.md.

::

    cellctl token add ann --role operator    # prints the token once; it never expires
    cellctl token add shift --role operator --expires 8h   # or --expires 2026-12-31T18:00
    cellctl audit --since 1h --who ann --json
"""

from __future__ import annotations

import contextlib
import os
import re
from datetime import datetime
from pathlib import Path
from typing import Any

import click
from rich.table import Table

from cellctl.clock import current_clock
from cellctl.errors import AccessDenied, UsageError, with_article
from cellctl.service.audit import RUNNING, AuditLog, keeps_trail
from cellctl.service.rpc import login_name
from cellctl.service.token import (
    DEFAULT_NAME,
    ROLES,
    TOKEN_ENV,
    TOKEN_FILE,
    add_token,
    check_unexpired,
    format_time,
    list_tokens,
    parse_expiry,
    revoke_token,
)
from cellctl.ui.calls import cell_call
from cellctl.ui.common import cell_dir, console, json_option, print_json, print_table, run

_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400}


def parse_since(text: str, now: float | None = None) -> float:
    """``--since``: a span back from now (``90s``, ``30m``, ``2h``, ``7d``) or a date and
    time (``2024-05-01`` or ``2024-05-01T14:30``); UsageError naming both forms."""
    now = current_clock().now() if now is None else now
    found = re.fullmatch(r"(\d{1,9})([smhd])", text.strip())
    if found:
        return now - int(found.group(1)) * _UNITS[found.group(2)]
    try:
        return datetime.fromisoformat(text.strip()).timestamp()
    except ValueError:
        raise UsageError(
            f"--since {text[:40]!r}: give a span (30m, 2h, 7d) or a date (2024-05-01T14:30)"
        ) from None


def _when(t: float) -> str:
    return format_time(t)


@click.group("token")
def token_group() -> None:
    """The control API's tokens: each with a name and a role."""


def _cell(ctx: click.Context) -> Path:
    """The cell directory of ``--cell``, refused as every other command refuses it when it
    is no cell (a mistyped --cell would get a tokens/ of its own, or "no tokens yet"). A
    directory a server ran in (its ``api-token``: a DNC shop's too) keeps its tokens."""
    from cellctl.service.client import require_cell

    directory = cell_dir(ctx)
    if not (directory / TOKEN_FILE).is_file():
        require_cell(directory)
    return directory


def _manager(directory: Path, method: str, params: dict[str, Any]) -> str:
    """Who changes the tokens: the token in ``$CELLCTL_TOKEN`` when one is set, which must be
    an engineer's (AccessDenied otherwise, as for every acting call, and the refused call
    with its ``params`` in the audit trail), else the local user (who owns the cell's
    files)."""
    from cellctl.service.client import env_caller

    given = os.environ.get(TOKEN_ENV, "").strip()
    if given:
        check_unexpired(directory, given)  # said as expired, with when, not as a wrong token
    caller = env_caller(directory)
    if caller is None:
        return f"local:{login_name()}"
    if caller.role != "engineer":
        name = caller.who.partition(":")[2]
        refused = f"{name} is {with_article(caller.role)}: {method} needs the engineer role"
        _audit(directory, caller.who, method, params, refused)
        raise AccessDenied(refused)
    return caller.who


def _audit(
    directory: Path, who: str, method: str, params: dict[str, Any], outcome: str = "ok"
) -> None:
    """Note a token change in the cell's audit trail, as the API's calls are: who may act is
    an engineer's concern too."""
    if not keeps_trail(directory):
        return
    with contextlib.closing(AuditLog(directory)) as log:
        log.record(who, method, params, outcome)


@token_group.command("add")
@click.argument("name")
@click.option(
    "--role",
    type=click.Choice(ROLES),
    required=True,
    help="viewer: read; operator: orders, alarms, pause; engineer: machines by hand too.",
)
@click.option(
    "--expires",
    metavar="SPAN|DATETIME",
    help="Refused from then on: a span from now (8h, 30d) or a local date and time "
    "(2026-12-31T18:00). Without it the token never expires (until revoked).",
)
@click.pass_context
def token_add(ctx: click.Context, name: str, role: str, expires: str | None) -> None:
    """Make token NAME with a role and print it once (only its hash is kept)."""
    directory = _cell(ctx)

    params: dict[str, Any] = {"name": name, "role": role}

    async def main() -> tuple[str, str, float | None]:
        # Read before anything else: a bad or past time is refused before a file is made.
        until = None if expires is None else parse_expiry(expires)
        if until is not None:
            # The audit trail keeps the time it came to, not "8h" of an unknown moment.
            params["expires"] = datetime.fromtimestamp(until).astimezone().isoformat("T", "seconds")
        who = _manager(directory, "token.add", params)
        return who, add_token(directory, name, role, until), until

    who, secret, until = run(main)
    _audit(directory, who, "token.add", params)
    console.print(secret, markup=False, soft_wrap=True)
    lasts = "never expires" if until is None else f"expires {_when(until)}"
    click.echo(
        f"token {name} ({role}, {lasts}): shown once, keep it; cellctl token revoke {name}",
        err=True,
    )


@token_group.command("list")
@json_option
@click.pass_context
def token_list(ctx: click.Context, as_json: bool) -> None:
    """The tokens: names, roles, when made and when they expire (never a secret)."""
    directory = _cell(ctx)

    async def main() -> tuple[list[Any], float]:
        return list_tokens(directory), current_clock().now()

    found, now = run(main)
    if as_json:
        print_json(
            [
                {
                    "name": e.name,
                    "role": e.role,
                    "created": e.created,
                    "expires": e.expires,  # unix seconds; null: never
                    "expired": e.expired(now),
                }
                for e in found
            ]
        )
        return
    if not found:
        console.print("no tokens yet: `cellctl run` enters api-token as `default`")
        return
    table = Table(title="API tokens")
    for column in ("Name", "Role", "Created", "Expires"):
        table.add_column(column)
    for e in found:
        table.add_row(e.name, e.role, _when(e.created), _expiry(e.expires, now))
    print_table(table)


def _expiry(expires: float | None, now: float) -> str:
    """A token's expiry as listed: "never", its date and time, "(expired)" once past."""
    if expires is None:
        return "never"
    return _when(expires) + (" (expired)" if now >= expires else "")


@token_group.command("revoke")
@click.argument("name")
@click.pass_context
def token_revoke(ctx: click.Context, name: str) -> None:
    """Revoke token NAME: refused from its next request on."""
    directory = _cell(ctx)

    async def main() -> str:
        who = _manager(directory, "token.revoke", {"name": name})
        revoke_token(directory, name)
        return who

    who = run(main)
    _audit(directory, who, "token.revoke", {"name": name})
    console.print(f"token {name} revoked", markup=False)
    if name == DEFAULT_NAME:
        # api-token went with it: what this computer's commands acted with.
        click.echo(
            f"{directory / TOKEN_FILE} removed with it: commands here act with $CELLCTL_TOKEN "
            "(an engineer's token) until `cellctl run` starts again and writes a new one",
            err=True,
        )


@click.command("audit")
@click.option("--since", help="A span back (30m, 2h, 7d) or a date (2024-05-01T14:30).")
@click.option("--who", help="One caller: a token's name or an OPC UA user.")
@click.option(
    "--limit",
    type=click.IntRange(1, 10_000),
    default=200,
    show_default=True,
    help="At most this many, the latest.",
)
@json_option
@click.pass_context
def audit_command(
    ctx: click.Context, since: str | None, who: str | None, limit: int, as_json: bool
) -> None:
    """Who did what to the cell, when, and how it ended."""
    params: dict[str, Any] = {"limit": limit}
    if since is not None:

        async def parse() -> float:
            return parse_since(since)

        params["since"] = max(0.0, run(parse))
    if who is not None:
        params["who"] = who
    found = cell_call(ctx, "audit.list", params)
    if as_json:
        print_json(found)
        return
    if not found:
        console.print("no actions recorded")
        return
    table = Table(title="Audit trail")
    for column in ("When", "Took", "Who", "Method", "Parameters", "Result"):
        table.add_column(column, overflow="fold")
    now = current_clock().now()
    for e in found:
        took = _took(e, now)
        table.add_row(_when(e["at"]), took, e["who"], e["method"], e["params"], e["result"])
    print_table(table)


def _took(entry: dict[str, Any], now: float) -> str:
    """How long an acting call took ("" for an entry written whole, or one whose end is
    unknown); one still running, how long so far. A server from before ``ended`` has none."""
    ended = entry.get("ended")
    if isinstance(ended, int | float):
        return f"{max(0.0, ended - entry['at']):.1f} s"
    if entry["result"] == RUNNING:
        return f"{max(0.0, now - entry['at']):.0f} s so far"
    return ""
