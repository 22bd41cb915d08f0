"""Why an order cannot go on: its parts' next moves need a machine out of service.

::

    reason = blocked_reason(config, parts, out_of_service=journal.machines_out_of_service())
    # "blocked: its parts need cnc2, out of service (taken out by the operator: tool change)"

An order is blocked when it has parts still to make, none of them is in a step now, and each
one that waits needs a machine out of service for its next move: the robot for any transfer,
and the mill of its next route step. An order not yet taken in (no parts) needs its route's
first mill and the robot. A held part waits for the operator, not for a machine: an order
with held parts is held, not blocked (unless its waiting parts are blocked too).
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
    indexes = [p.route_index for p in waiting] or [0]
    missing: dict[str, str] = {}
    for index in indexes:
        out = [m for m in needs(config, part_type, index) if m in out_of_service]
        if not out:
            return ""  # this part can move
        for m in out:
            missing[m] = out_of_service[m]
    why = "; ".join(f"{m}, out of service ({r or 'no reason given'})" for m, r in missing.items())
    return f"blocked: its parts need {why}"
