"""What the console's traffic pane shows of a machine: its last rows both ways, through the
client's ``traffic.tail``, the first bytes sent for the operator's own last command kept on
top however many rows its answer takes::

    commands["robot"] = clock.now()          # the operator's command, given now
    rows, command = await traffic_rows(client, "robot", commands)
    pane.show("robot", rows, command)
    command_ended(commands, "robot", since, clock.now())   # its answer came: no later bytes

A command's mark is when it was given (its first row sent after is looked for), then, once
its answer has come, the span from its start to its answer (a row sent later is someone
else's: another client's transfer), then that first row itself once found.
"""

from __future__ import annotations

from typing import Any

from cellctl.service.client import CellClient

#: Rows the pane has room for.
PANE_ROWS = 4
#: How far back the first bytes of the operator's command are looked for.
LOOK_BACK = 2000

#: Per machine, the operator's own last command: when it was given (its answer not come
#: yet), the span from then to its answer, or the first row it sent once found.
Commands = dict[str, float | tuple[float, float] | dict[str, Any]]


def command_ended(commands: Commands, name: str, since: float, until: float) -> None:
    """The command on ``name`` given at ``since`` has had its answer at ``until``: its own
    bytes are those sent in between (a later row is not its own). Nothing changes when its
    first row is found already, or another command has been given since."""
    if commands.get(name) == since:
        commands[name] = (since, until)


async def traffic_rows(
    client: CellClient, name: str, commands: Commands
) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
    """``name``'s last rows, and the first row sent for the operator's last command (None if
    none). ``commands[name]``: when the command was given, or the span until its answer (its
    first row sent is looked for, then kept there in its place; a command that ended having
    sent none has none, and the next rows sent are not taken for it)."""
    mark = commands.get(name)
    if mark is not None and not isinstance(mark, dict):
        since, until = mark if isinstance(mark, tuple) else (mark, None)
        rows = await client.call("traffic.tail", {"machine": name, "limit": LOOK_BACK})
        sent = [
            r
            for r in rows
            if r.get("dir") == ">>"
            and r.get("time", 0) >= since
            and (until is None or r.get("time", 0) <= until)
        ]
        if sent:
            commands[name] = sent[0]
        elif until is not None and commands.get(name) == mark:
            del commands[name]  # it ended and sent nothing: no row is its own
    own = commands.get(name)
    command = own if isinstance(own, dict) else None
    limit = PANE_ROWS - 1 if command else PANE_ROWS
    rows = await client.call("traffic.tail", {"machine": name, "limit": limit})
    return [r for r in rows if r != command], command
