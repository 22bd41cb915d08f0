"""What the console's traffic pane shows of a machine: its last rows both ways, through the
client's ``traffic.tail``, the first bytes sent for the operator's own last command kept on
top however many rows its answer takes::

    commands["robot"] = clock.now()          # the operator's command, given now
    rows, command = await traffic_rows(client, "robot", commands)
    pane.show("robot", rows, command)
"""

from __future__ import annotations

from typing import Any

from cellctl.service.client import CellClient

#: Rows the pane has room for.
PANE_ROWS = 4
#: How far back the first bytes of the operator's command are looked for.
LOOK_BACK = 2000


async def traffic_rows(
    client: CellClient, name: str, commands: dict[str, float | dict[str, Any]]
) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
    """``name``'s last rows, and the first row sent for the operator's last command (None if
    none). ``commands[name]``: when the command was given (its first row sent is looked for
    once, then kept there in its place)."""
    mark = commands.get(name)
    if mark is not None and isinstance(mark, float):
        rows = await client.call("traffic.tail", {"machine": name, "limit": LOOK_BACK})
        sent = [r for r in rows if r.get("dir") == ">>" and r.get("time", 0) >= mark]
        if sent:
            commands[name] = sent[0]
    own = commands.get(name)
    command = own if isinstance(own, dict) else None
    limit = PANE_ROWS - 1 if command else PANE_ROWS
    rows = await client.call("traffic.tail", {"machine": name, "limit": limit})
    return [r for r in rows if r != command], command
