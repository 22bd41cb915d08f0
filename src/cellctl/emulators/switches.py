"""An emulator's fault switches, checked as ``--fault NAME[=ARG]`` gives them::

    FAULTS = {"stall": "CTS stuck low ...", "drop": "=N: drop the connection N lines in ..."}
    check_switch(FAULTS, "stall", "abc")   # UsageError: fault stall takes no argument ...

A switch takes an argument exactly when its description in the table starts with ``=``
(``=N: ...``): the table a help text shows is the one fact the check reads. One whose argument
may be left out says the value it then takes the same way, in its description: ``(default 5
lines)``; :func:`default_of` reads it, and what a switch switched on says names it::

    default_of(FAULTS, "drop")              # "5 lines"
    said_on("cnc1", "drop", None, FAULTS)   # "cnc1: drop on (5 lines, its default)"
    said_switched_on("drop", "3", FAULTS)   # "drop=3 on" (a single machine's emulator)

A cell's switches, ``MACHINE:NAME[=ARG]`` as ``cellctl emulate cell --fault`` takes them, are
checked against each machine's table before anything is written or started::

    check_fault("cnc1:stal", {"robot": ROBOT_FAULTS, "cnc1": MILL_FAULTS, "plc": PLC_FAULTS})
    # UsageError: fault 'cnc1:stal': unknown fault 'stal' for cnc1; known: stall, ...
"""

from __future__ import annotations

import re
from collections.abc import Mapping

from cellctl.errors import UsageError


def takes_argument(faults: Mapping[str, str], name: str) -> bool:
    """True if switch ``name`` of ``faults`` takes an argument (its description: ``=ARG: ...``)."""
    return faults.get(name, "").startswith("=")


#: Where a description says the value its switch takes without ``=ARG``: ``(default 16 ms)``.
_DEFAULT = re.compile(r"\(default ([^)]+)\)")


def default_of(faults: Mapping[str, str], name: str) -> str | None:
    """The value switch ``name`` of ``faults`` takes when ``=ARG`` is left out, as its
    description says it (``"=MS: ... (default 16 ms)"`` -> ``"16 ms"``); None for a switch
    that takes no argument, or one that must be given it."""
    if not takes_argument(faults, name):
        return None
    found = _DEFAULT.search(faults[name])
    return found.group(1).strip() if found else None


def shown_switch(faults: Mapping[str, str], name: str, arg: str | None) -> str:
    """Switch ``name`` as it is on: ``"drop=3"``, ``"drop (5 lines, its default)"`` (its
    argument left out), ``"stall"``."""
    if arg is not None:
        return f"{name}={arg}"
    default = default_of(faults, name)
    return name if default is None else f"{name} ({default}, its default)"


def said_on(machine: str, name: str, arg: str | None, faults: Mapping[str, str]) -> str:
    """What switching ``name`` on at ``machine`` did, in a line: ``"cnc1: drop=3 on"``,
    ``"cnc1: adapter-latency on (16 ms, its default)"``: a default taken is said, never
    silent."""
    return f"{machine}: {said_switched_on(name, arg, faults)}"


def said_switched_on(name: str, arg: str | None, faults: Mapping[str, str]) -> str:
    """What switching ``name`` on did, in the words of :func:`said_on` without a machine's
    name (a single machine's emulator, where there is one): ``"drop=3 on"``, ``"drop on
    (5 lines, its default)"``."""
    default = default_of(faults, name) if arg is None else None
    if default is not None:
        return f"{name} on ({default}, its default)"
    return f"{shown_switch(faults, name, arg)} on"


def check_switch(faults: Mapping[str, str], name: str, arg: str | None) -> None:
    """Refuse a switch the table does not have (naming those it has), or an argument given
    to a switch that takes none, in words (:class:`UsageError`)."""
    if name not in faults:
        raise UsageError(f"unknown fault {name!r}; known: {', '.join(faults)}")
    if arg is not None and not takes_argument(faults, name):
        raise UsageError(f"fault {name} takes no argument, not {arg!r}")


def parse_fault(text: str) -> tuple[str, str | None]:
    """``"corrupt-checksum=3"`` → ``("corrupt-checksum", "3")``; ``"drop"`` → ``("drop", None)``."""
    name, sep, arg = text.partition("=")
    name = name.strip()
    if not name:
        raise UsageError(f"fault {text!r}: write NAME or NAME=VALUE")
    return name, (arg.strip() if sep else None)


def split_fault(text: str) -> tuple[str, str, str | None]:
    """``"cnc1:drop=3"`` → ``("cnc1", "drop", "3")``; UsageError for text without a machine."""
    machine, sep, rest = text.partition(":")
    if not sep:
        raise UsageError(f"fault {text!r}: write MACHINE:NAME[=ARG], e.g. cnc1:stall")
    name, arg = parse_fault(rest)
    return machine, name, arg


def check_fault(
    text: str, machines: Mapping[str, Mapping[str, str]]
) -> tuple[str, str, str | None]:
    """Check a cell's switch ``MACHINE:NAME[=ARG]`` against ``machines`` (each machine's name
    and its fault table; ``plc`` for the PLC) without a running cell: the machine, the
    switch's name and whether it takes an argument. Returns ``(machine, name, arg)``;
    UsageError naming the machines or the switches there are."""
    machine, name, arg = split_fault(text)
    faults = machines.get(machine)
    if faults is None:
        raise UsageError(f"fault {text!r}: no machine {machine!r} ({', '.join(machines)})")
    if name not in faults:
        raise UsageError(
            f"fault {text!r}: unknown fault {name!r} for {machine}; known: {', '.join(faults)}"
        )
    if arg is not None and not takes_argument(faults, name):
        raise UsageError(f"fault {text!r}: {name} takes no argument, not {arg!r}")
    return machine, name, arg


__all__ = [
    "check_fault",
    "check_switch",
    "default_of",
    "parse_fault",
    "said_on",
    "said_switched_on",
    "shown_switch",
    "split_fault",
    "takes_argument",
]
