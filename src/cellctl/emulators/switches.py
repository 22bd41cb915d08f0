"""An emulator's fault switches, checked as ``--fault NAME[=ARG]`` gives them::

    FAULTS = {"stall": "CTS stuck low ...", "drop": "=N: drop the connection N lines in ..."}
    check_switch(FAULTS, "stall", "abc")   # UsageError: fault stall takes no argument ...

A switch takes an argument exactly when its description in the table starts with ``=``
(``=N: ...``): the table a help text shows is the one fact the check reads.
"""

from __future__ import annotations

from collections.abc import Mapping

from cellctl.errors import UsageError


def takes_argument(faults: Mapping[str, str], name: str) -> bool:
    """True if switch ``name`` of ``faults`` takes an argument (its description: ``=ARG: ...``)."""
    return faults.get(name, "").startswith("=")


def check_switch(faults: Mapping[str, str], name: str, arg: str | None) -> None:
    """Refuse a switch the table does not have (naming those it has), or an argument given
    to a switch that takes none, in words (:class:`UsageError`)."""
    if name not in faults:
        raise UsageError(f"unknown fault {name!r}; known: {', '.join(faults)}")
    if arg is not None and not takes_argument(faults, name):
        raise UsageError(f"fault {name} takes no argument, not {arg!r}")


__all__ = ["check_switch", "takes_argument"]
