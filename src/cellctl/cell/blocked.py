"""Why an order cannot go on: its parts' next moves need a machine out of service.

::

    reason = blocked_reason(config, parts, out_of_service=journal.machines_out_of_service())
    # "blocked: its parts need cnc2, out of service (taken out by the operator: tool change)"

An order is blocked when it has parts still to make, none of them is in a step now, and each
one that waits needs a machine out of service for its next move: the robot for any transfer,
and the mill of its next route step. An order not yet taken in (no parts) needs its route's
first mill and the robot. A held part waits for the operator, not for a machine: an order
with held parts is held, not blocked (unless its waiting parts are blocked too). A part whose
next mill holds another part of the order that cannot leave (it waits for a machine out of
service) is blocked with it: the mill is not out, but it will not be free.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from cellctl.cell.config import CellConfig
from cellctl.cell.journal import Part


def needs(config: CellConfig, part_type: str, route_index: int) -> list[str]:
    """The machines the next move of a part of ``part_type`` at ``route_index`` needs."""
    out = [config.robot.name]
    part = config.parts.get(part_type)
    if part is not None and route_index < len(part.route):
        out.append(part.route[route_index].mill)
    return out


def blocked_reason(
    config: CellConfig,
    part_type: str,
    parts: Sequence[Part],
    out_of_service: Mapping[str, str],
) -> str:
    """Why the order of ``part_type`` with ``parts`` (none: not taken in yet) cannot go on;
    "" when it can (or is not waiting for a machine)."""
    if not out_of_service:
        return ""
    if any(p.status == "active" for p in parts):
        return ""
    waiting = [p for p in parts if p.status == "waiting"]
    if parts and not waiting:
        return ""
    mills = {m.name for m in config.mills}
    missing: dict[str, str] = {}
    held: dict[str, str] = {}  # a mill -> the part of this order in it that cannot leave
    stuck: set[int] = set()
    blocking: set[str] = set()  # held mills a part of the order waits for
    pending = list(range(len(waiting))) if waiting else [-1]  # -1: the order not taken in
    while True:  # parts blocked by the parts that block their next mill, to a fixed point
        for i in pending:
            index = waiting[i].route_index if i >= 0 else 0
            wanted = needs(config, part_type, index)
            out = [m for m in wanted if m in out_of_service]
            full = [m for m in wanted if m in held]
            if not out and not full:
                continue
            stuck.add(i)
            blocking.update(full)
            for m in out:
                missing[m] = out_of_service[m]
            if i >= 0 and waiting[i].location in mills:
                held.setdefault(waiting[i].location, waiting[i].id)
        left = [i for i in pending if i not in stuck]
        if len(left) == len(pending) or not left:
            break
        pending = left
    if len(stuck) < max(len(waiting), 1) or not missing:
        return ""  # a part can move
    why = "; ".join(f"{m}, out of service ({r or 'no reason given'})" for m, r in missing.items())
    occupied = "".join(f"; {m} holds {held[m]}, which cannot leave" for m in sorted(blocking))
    return f"blocked: its parts need {why}{occupied}"
