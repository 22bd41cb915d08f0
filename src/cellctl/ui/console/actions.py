"""What the console can do, declared once: each acting method of the control API and where
the operator finds it in the menus.

The cell's actions are listed here; a machine's functions are its kind's menu (the same
list the machine menus are built from). The console calls no acting method missing here
(``ConsoleApp.call`` refuses it), and the parity test reads this against the API's method
table. (A server that is no cell controller declares its machines' methods itself, in
``machines.functions``: :mod:`cellctl.ui.console.served` offers exactly those.)::

    console_actions()["cell.estop"]     # ("CELL", "EMERGENCY STOP")
    console_actions()["robot.go"]       # ("ROBOT", "GO")
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from cellctl.errors import with_article
from cellctl.kinds import registry
from cellctl.service.functions import kind_menu
from cellctl.service.token import role_allows

#: The cell's acting API methods and their place: (menu, entry[, choice in its dialog]).
CELL_ACTIONS: dict[str, tuple[str, ...]] = {
    "cell.pause": ("CELL", "PAUSE"),
    "cell.resume": ("CELL", "RESUME"),
    "cell.estop": ("CELL", "EMERGENCY STOP"),  # asks for the reason
    "orders.submit": ("CELL", "SUBMIT ORDER"),
    "orders.cancel": ("CELL", "CANCEL ORDER"),  # also Enter on an order in ORDERS
    "alarms.ack": ("CELL", "ALARMS", "ACKNOWLEDGE"),
    "alarms.shelve": ("CELL", "ALARMS", "SHELVE FOR 1 HOUR"),
    "alarms.clear": ("CELL", "ALARMS", "CLEAR"),
    "alarms.unshelve": ("CELL", "ALARMS", "UNSHELVE"),  # offered for a shelved alarm
    "parts.release": ("CELL", "HELD PARTS", "RELEASE"),
    "parts.scrap": ("CELL", "HELD PARTS", "SCRAP"),
    # A machine's own menu, key s (asks for the reason).
    "machines.out_of_service": ("MACHINE", "OUT OF SERVICE"),
    "machines.return_to_service": ("MACHINE", "RETURN TO SERVICE"),
}


def console_actions() -> dict[str, tuple[str, ...]]:
    """Every acting method the console offers: the cell's, and each installed kind's
    functions as its machine menu shows them (``("ROBOT", "GO")``)."""
    found = dict(CELL_ACTIONS)
    for kind in registry.kinds():
        for fn in kind_menu(kind.name):
            found.setdefault(f"{fn.family}.{fn.name}", (fn.family.upper(), fn.label))
    return found


def role_refusal(info: Mapping[str, Any], method: str) -> str | None:
    """Why the caller ``server.info`` names (its answer: ``info``) may not call ``method``, in
    the server's own words; None if it may, or if the server does not say (an older one:
    the call itself is refused then)."""
    caller, roles = info.get("caller"), info.get("roles")
    if not isinstance(caller, dict) or not isinstance(roles, dict) or method not in roles:
        return None
    role, needed = str(caller.get("role", "")), str(roles[method])
    if role_allows(role, needed):
        return None
    who = str(caller.get("who", ""))
    name = who.partition(":")[2] or who
    return f"{name} is {with_article(role)}: {method} needs the {needed} role"
