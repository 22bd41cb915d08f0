"""What a planner adds to a plan on the command line, read and checked before anything runs.

::

    add = parse_add("wax-robot-base:40@5")              # AddSpec(part, qty 40, priority 5)
    add = parse_add("wax-robot-base:40 by FRI 18:00", start)   # ... due the next Friday 18:00
    window = parse_fault("cnc2:down@10:00-11:00", start) # FaultWindow(cnc2, down, 10:00, 11:00)
    check_inputs(config, orders, faults, policy)        # UsageError naming what the cell lacks

``--fault MACHINE:FAULT[=ARG]@WHEN[-WHEN]``: ``down`` takes the machine out of service over
the window; any other name is one of the machine's emulator fault switches (``cellctl
emulate cell --help`` lists them). Without an end the fault lasts to the end of the plan.

``--add PART:QTY[@PRIORITY][ by WHEN]``: ``WHEN`` is a due time as ``--until`` and ``cellctl
submit --due`` write it, seen from the plan's start; the plan says whether the order is done
by it.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from cellctl.cell.config import CellConfig, load_cell
from cellctl.cell.scheduler import DOWNSTREAM_FIRST
from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.mailbox.base import MAX_QTY, check_due
from cellctl.plan.engine import POLICIES, FaultWindow, HeldPart, PlanInputs, PlanOrder
from cellctl.plan.faults import PLC, check_switch, switches
from cellctl.plan.when import (
    PLAN_POLL_S,
    parse_duration,
    parse_poll,
    resolve_when,
    skipped,
    when_text,
)

#: Priorities an order may have (the control API's range).
PRIORITY_RANGE: Final = range(-1_000_000, 1_000_001)
#: ``--policy all``: every policy, compared.
ALL_POLICIES: Final = "all"

_WORD = r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,99}"
_ADD = re.compile(
    rf"^\s*(?P<part>{_WORD})\s*:\s*(?P<qty>\d{{1,9}})\s*(?:@\s*(?P<prio>[-+]?\d{{1,18}}))?"
    r"(?:\s+[Bb][Yy]\s+(?P<due>\S.{0,59}?))?\s*$"
)
#: How ``--add`` is written, for its refusals.
ADD_FORMS: Final = (
    "write PART:QTY[@PRIORITY][ by WHEN], e.g. wax-robot-base:40, wax-robot-base:40@5 or "
    "wax-robot-base:40@5 by FRI 18:00"
)
#: A fault window's time: ``[DAY ]HH:MM`` or a date and time (``2026-11-30T06:30``).
_WHEN = r"(?:\d{4}-\d{2}-\d{2}[T ]\d{1,2}:\d{2}(?::\d{2})?|(?:[A-Za-z]{3,9}\s+)?\d{1,2}:\d{2})"
_FAULT = re.compile(
    rf"^\s*(?P<machine>{_WORD})\s*:\s*(?P<name>[a-z][a-z0-9_\-]{{0,40}})(?:=(?P<arg>[^@\s]{{1,40}}))?"
    rf"\s*@\s*(?P<a>{_WHEN})\s*(?:-\s*(?P<b>{_WHEN}))?\s*$"
)


@dataclass(frozen=True)
class AddSpec:
    """``--add PART:QTY[@PRIORITY][ by WHEN]``: an order added to the plan, due at ``due``
    (unix seconds) if given."""

    part_type: str
    qty: int
    priority: int = 0
    due: float | None = None


def parse_add(text: str, start: float | None = None) -> AddSpec:
    """``wax-robot-base:40``, ``wax-robot-base:40@5`` (priority: higher goes first), either
    with `` by WHEN`` (``wax-robot-base:40@5 by FRI 18:00``): due at ``WHEN``, read as
    ``cellctl submit --due`` reads it, from the plan's ``start`` (None: now, to check the
    form before the plan's start is known). A date and time may be past already: the order
    is late from the start, as an orders file's is."""
    found = _ADD.match(text)
    if found is None:
        raise UsageError(f"--add {text!r}: {ADD_FORMS}")
    qty = int(found["qty"])
    if not 1 <= qty <= MAX_QTY:
        raise UsageError(f"--add {text!r}: the quantity must be 1 to {MAX_QTY}")
    priority = int(found["prio"] or 0)
    if priority not in PRIORITY_RANGE:
        raise UsageError(f"--add {text!r}: the priority must be -1000000 to 1000000")
    due = None
    if found["due"] is not None:
        seen_from = current_clock().now() if start is None else start
        try:
            due = check_due(resolve_when(found["due"], seen_from, due=True))
        except UsageError as e:
            # The time's own words (``hours 0-23`` ...), then how the whole is written.
            why = str(e)
            why = f"due {why}" if why.startswith("time ") else why
            raise UsageError(
                f"--add {text!r}: {why} (an order with a due time: PART:QTY[@PRIORITY] by "
                "WHEN, e.g. wax-robot-base:40@5 by FRI 18:00)"
            ) from None
    return AddSpec(found["part"], qty, priority, due)


def parse_fault(text: str, start: float, until: float | None = None) -> FaultWindow:
    """``cnc2:down@10:00-11:00``, ``cnc1:stall@FRI 09:30-FRI 10:00``, ``plc:stuck-door=2@10:00``,
    ``cnc1:down@2026-11-30T06:30-2026-11-30T08:00``: ``[DAY ]HH:MM`` is the next such local
    time at or after the plan's ``start`` (the end at or after the window's start; a wall
    time the clocks skip, the next that exists), a date and time is itself. Refused if the
    window ends as it opens, or opens at or after ``until``: saying how each time was read."""
    found = _FAULT.match(text)
    if found is None:
        raise UsageError(
            f"--fault {text!r}: write MACHINE:FAULT@FROM-TO, each time HH:MM, DAY HH:MM or "
            "a date and time (e.g. cnc2:down@10:00-11:00, cnc2:down@2026-11-30T10:00-11:00); "
            "FAULT is down or an emulator fault switch, NAME=ARG if it takes an argument"
        )
    if found["b"] and " ".join(found["a"].lower().split()) == " ".join(found["b"].lower().split()):
        # Read as written, it would be a window of a whole day (or week): never what was meant.
        raise UsageError(f"--fault {text!r}: the window ends as it opens: write when it ends")
    opens = resolve_when(found["a"], start, inclusive=True)
    # At or after the start: an end that reads as the very instant (its start was a wall
    # time the clocks skip) is refused, not read as the next day's.
    closes = resolve_when(found["b"], opens, inclusive=True) if found["b"] else None
    read = f"{found['a']} read as {when_text(opens, date=True)}{skipped(found['a'], opens)}"
    if closes is not None:
        read += f", {found['b']} as {when_text(closes, date=True)}{skipped(found['b'], closes)}"
    if closes is not None and closes <= opens:
        raise UsageError(
            f"--fault {text!r}: the window ends as it opens ({read}): write when it ends"
        )
    if until is not None and opens >= until:
        raise UsageError(
            f"--fault {text!r}: the window opens after the plan ends "
            f"({when_text(until, date=True)}): {read}, the next such time at or after the "
            f"plan's start ({when_text(start, date=True)}); give a date for another "
            "(2026-11-30T06:30)"
        )
    return FaultWindow(found["machine"], found["name"], opens, closes, found["arg"])


def fault_switches(config: CellConfig) -> dict[str, tuple[str, ...]]:
    """Each machine's faults a plan may put on it: ``down`` (not the PLC's) and its emulator's
    fault switches (its kind's, from the registry)."""
    found = {m.name: switches(m.kind) for m in [config.robot, *config.mills]}
    found[PLC] = switches(None)
    return found


def check_inputs(
    config: CellConfig,
    orders: Iterable[PlanOrder],
    faults: Iterable[FaultWindow],
    policies: Sequence[str] = (),
    until: float | None = None,
) -> None:
    """Refuse, naming what the cell has, an order of a part type the cell does not make, a
    fault on a machine it does not have or a fault its emulator does not know, and an unknown
    policy: before anything runs."""
    for order in orders:
        if order.part_type not in config.parts:
            known = ", ".join(config.parts) or "none"
            raise UsageError(
                f"order {order.order_id}: the cell makes no {order.part_type!r} (known: {known})"
            )
    kinds: dict[str, str | None] = {m.name: m.kind for m in [config.robot, *config.mills]}
    kinds[PLC] = None
    for window in faults:
        if window.machine not in kinds:
            raise UsageError(
                f"fault on {window.machine!r}: the cell has no such machine "
                f"(known: {', '.join(kinds)})"
            )
        # Its name and argument as the machine's emulator takes them (the same words).
        check_switch(window.machine, kinds[window.machine], window.fault, window.arg)
        if window.end is not None and window.end <= window.start:
            raise UsageError(
                f"fault {window.fault!r} on {window.machine}: it ends before it starts"
            )
        if until is not None and window.start >= until:
            raise UsageError(
                f"fault {window.fault!r} on {window.machine}: the window opens after the plan "
                f"ends ({when_text(until, date=True)}): at {when_text(window.start, date=True)}"
            )
    _check_names(policies)
    twice = named_twice(policies)
    if twice:
        raise UsageError(f"policies {', '.join(policies)}: {twice}")


def named_twice(policies: Sequence[str]) -> str | None:
    """What is wrong with a list of policies that names one twice (``default`` is
    ``downstream-first``: the two are one), in words; None if each is named once. A policy
    is played once: twice, it would be the same plan again in the comparison (and in the
    same directory)."""
    seen: dict[str, str] = {}
    for policy in policies:
        same = DOWNSTREAM_FIRST if policy == "default" else policy
        if same not in seen:
            seen[same] = policy
        elif seen[same] == policy:
            return f"{policy} is named twice: name each policy once"
        else:
            return f"default is {DOWNSTREAM_FIRST}: name it once, or it is played twice"
    return None


def _check_names(policies: Iterable[str]) -> None:
    for policy in policies:
        if policy not in POLICIES:
            known = ", ".join([*POLICIES, ALL_POLICIES])
            raise UsageError(f"policy {policy!r}: unknown (known: {known})")


def policies_of(text: str) -> tuple[str, ...]:
    """``--policy NAME``, ``--policy A,B`` or ``--policy all`` (every policy): the policies
    to play, compared side by side when more than one (each named once: ``default,default``
    is refused as ``default,downstream-first`` is), each name known (a typo is refused
    here, once, not per cell of a factory; :func:`check_inputs` checks them again for a
    replayed file's)."""
    if text == ALL_POLICIES:  # each once: "default" names one of the others
        return tuple(p for p in POLICIES if p != "default")
    named = [p.strip() for p in text.split(",") if p.strip()]
    if not named:
        raise UsageError("--policy: name a policy (or all)")
    if ALL_POLICIES in named:
        raise UsageError(f"--policy {text!r}: all plays every policy: name it alone")
    _check_names(named)
    twice = named_twice(named)
    if twice:
        raise UsageError(f"--policy {text!r}: {twice}")
    return tuple(named)


def fresh_ids(taken: Iterable[str], count: int, prefix: str = "plan-add") -> list[str]:
    """``count`` order ids not in ``taken``: ``plan-add1``, ``plan-add2`` ..."""
    used = set(taken)
    out: list[str] = []
    n = 0
    while len(out) < count:
        n += 1
        candidate = f"{prefix}{n}"
        if candidate not in used:
            out.append(candidate)
    return out


#: A plan's horizon when neither ``--shift`` nor ``--until`` is given: one shift.
DEFAULT_SHIFT: Final = "8h"


def plan_window(start: float, shift: str | None, until: str | None) -> float:
    """The plan's end: ``start`` plus ``--shift`` (default 8 h), or ``--until``."""
    if shift is not None and until is not None:
        raise UsageError("give --shift or --until, not both")
    if until is not None:
        return resolve_when(until, start)
    return start + parse_duration(shift if shift is not None else DEFAULT_SHIFT)


def plan_inputs(
    cell_dir: Path,
    *,
    start: float,
    shift: str | None = None,
    until: str | None = None,
    orders: Sequence[PlanOrder] = (),
    adds: Sequence[str] = (),
    faults: Sequence[str] = (),
    policy: str = "default",
    seed: int = 0,
    out_of_service: Sequence[str] = (),
    held: Sequence[HeldPart] = (),
    poll_period: float = PLAN_POLL_S,
) -> tuple[PlanInputs, tuple[str, ...]]:
    """A plan's inputs from what a planner typed (``--add``, ``--fault`` ... texts), checked
    against the cell in ``cell_dir``: every refusal comes before anything runs."""
    if not 0 <= seed < 2**63:
        raise UsageError(f"--seed {seed}: a whole number 0 or more")
    poll_period = parse_poll(poll_period)
    end = plan_window(start, shift, until)
    added = [parse_add(text, start) for text in adds]
    ids = fresh_ids([o.order_id for o in orders], len(added))
    every = (
        *orders,
        *(
            PlanOrder(i, a.part_type, a.qty, a.priority, a.due)
            for i, a in zip(ids, added, strict=True)
        ),
    )
    if not every and held:
        # Open orders there are: their parts all wait for the operator's word, which a plan
        # does not guess (held parts stay held), so nothing of them would play.
        count = len({h.order_id for h in held})
        orders_word = "open order" if count == 1 else "open orders"
        raise UsageError(
            f"nothing to plan: {count} {orders_word}, every part held: nothing plays until "
            "the operator releases them (cellctl part release PART)"
        )
    if not every:
        raise UsageError(
            "nothing to plan: no open orders (submit some, or add some to a cell's plan: "
            "cellctl plan --add PART:QTY)"
        )
    windows = tuple(parse_fault(text, start) for text in faults)
    policies = policies_of(policy)
    config = load_cell(cell_dir)
    check_inputs(config, every, windows, policies)
    for text in faults:  # a window after the plan's end, refused saying how it was read
        parse_fault(text, start, end)
    inputs = PlanInputs(
        cell_dir=cell_dir,
        orders=every,
        start=start,
        until=end,
        faults=windows,
        policy=policies[0],
        seed=seed,
        poll_period=poll_period,
        out_of_service=tuple(out_of_service),
        held=tuple(held),
    )
    return inputs, policies
