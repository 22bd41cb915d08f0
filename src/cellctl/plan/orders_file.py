"""The orders file of ``cellctl plan --dir DIR --orders FILE``: CSV, one order a line.

::

    # orders for the week (lines starting with # are comments)
    id,part_type,qty,priority,due
    A,wax-robot-base,20,5,FRI 18:00
    B,wax-toy-mill-table,10,,2026-11-27T12:00
    C,wax-robot-base,4

The header names the columns (``id``, ``part_type`` and ``qty`` needed; ``priority`` and
``due`` optional, in any order); an empty cell takes the default (priority 0, no due time).
``due`` is written as ``--until`` is: ``FRI 18:00``, ``18:00`` (the next such time after the
plan's start) or a date and time, which may lie before the plan's start (the order is late
already) or past its end.
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Collection
from pathlib import Path
from typing import Final

from cellctl.errors import UsageError
from cellctl.files import read_file
from cellctl.mailbox.base import MAX_QTY, check_new_order
from cellctl.plan.engine import PlanOrder
from cellctl.plan.spec import PRIORITY_RANGE
from cellctl.plan.when import resolve_when

#: Columns an orders file must have, and may have.
REQUIRED: Final = ("id", "part_type", "qty")
OPTIONAL: Final = ("priority", "due")
#: The largest orders file read, bytes, and the most orders in it.
MAX_BYTES: Final = 1_000_000
MAX_ORDERS: Final = 10_000


def read_orders_file(
    path: Path, start: float, part_types: Collection[str] | None = None
) -> tuple[PlanOrder, ...]:
    """The orders in ``path`` (see the module docstring); due times seen from ``start``;
    ``part_types``: what the cell makes (an order of another is refused at its line)."""
    try:
        data = read_file(path, limit=MAX_BYTES)
    except FileNotFoundError:
        raise UsageError(f"{path}: no such orders file") from None
    except OSError as e:
        raise UsageError(f"{path}: cannot read: {e.strerror}") from None
    if len(data) > MAX_BYTES:
        raise UsageError(f"{path}: larger than {MAX_BYTES} bytes: not an orders file")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        # A spreadsheet's plain "CSV" is often its own code page (an accent, a degree sign):
        # said where, and how to save it, as any refusal of a line is.
        line = data.count(b"\n", 0, e.start) + 1
        raise UsageError(
            f"{path}, line {line}: not UTF-8 text (byte {e.start + 1}): save the file as "
            'UTF-8 (a spreadsheet\'s "CSV UTF-8")'
        ) from None
    return parse_orders(text, start, str(path), part_types)


def parse_orders(
    text: str, start: float, name: str = "orders", part_types: Collection[str] | None = None
) -> tuple[PlanOrder, ...]:
    """The orders in CSV ``text`` (see the module docstring); ``name`` for the messages;
    ``part_types`` as :func:`read_orders_file`'s."""
    if "\x00" in text:
        raise UsageError(f"{name}: not a text file (a NUL byte)")
    numbered = [
        (n, line)
        for n, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not numbered:
        raise UsageError(f"{name}: no orders (write a header: id,part_type,qty,priority,due)")
    try:
        rows = list(csv.reader(io.StringIO("\n".join(line for _, line in numbered))))
    except csv.Error as e:
        raise UsageError(f"{name}: not CSV: {e}") from None
    header = [h.strip().lower() for h in rows[0]]
    where = f"{name}, line {numbered[0][0]}"
    missing = [c for c in REQUIRED if c not in header]
    unknown = [c for c in header if c not in (*REQUIRED, *OPTIONAL)]
    if missing or unknown or len(set(header)) != len(header):
        raise UsageError(
            f"{where}: the header must name the columns id,part_type,qty and optionally "
            f"priority,due, once each (found: {','.join(header)[:200]})"
        )
    if len(rows) - 1 > MAX_ORDERS:
        raise UsageError(f"{name}: more than {MAX_ORDERS} orders")
    orders: list[PlanOrder] = []
    seen: set[str] = set()
    for (number, _), row in zip(numbered[1:], rows[1:], strict=False):
        where = f"{name}, line {number}"
        # Fewer fields are the optional columns left out; not a needed one ("qty must be a
        # whole number, not ''" would not say the field is missing).
        short = [c for c in REQUIRED if header.index(c) >= len(row)]
        if len(row) > len(header) or short:
            lacking = f" (no {', '.join(short)})" if short else ""
            raise UsageError(f"{where}: {len(row)} fields, the header names {len(header)}{lacking}")
        cells = dict(zip(header, (c.strip() for c in row), strict=False))
        order = _order(cells, start, where)
        if part_types is not None and order.part_type not in part_types:
            known = ", ".join(part_types) or "none"
            raise UsageError(f"{where}: the cell makes no {order.part_type!r} (it makes: {known})")
        if order.order_id in seen:
            raise UsageError(f"{where}: order {order.order_id} is in the file twice")
        seen.add(order.order_id)
        orders.append(order)
    return tuple(orders)


def _order(cells: dict[str, str], start: float, where: str) -> PlanOrder:
    order_id, part_type = cells.get("id", ""), cells.get("part_type", "")
    if not order_id or not part_type:
        raise UsageError(f"{where}: an order needs an id and a part type")
    if len(order_id) > 100 or len(part_type) > 100:
        raise UsageError(f"{where}: an id or part type is at most 100 characters")
    qty = _integer(cells.get("qty", ""), "qty", where)
    if not 1 <= qty <= MAX_QTY:
        raise UsageError(f"{where}: qty must be 1 to {MAX_QTY}, not {qty}")
    priority = _integer(cells.get("priority") or "0", "priority", where)
    if priority not in PRIORITY_RANGE:
        raise UsageError(f"{where}: priority must be -1000000 to 1000000")
    try:
        check_new_order(part_type, qty, priority, order_id)
    except UsageError as e:
        raise UsageError(f"{where}: {e}") from None
    due_text = cells.get("due") or ""
    try:
        due = resolve_when(due_text, start, due=True) if due_text else None
    except UsageError as e:
        raise UsageError(f"{where}: due: {e}") from None
    return PlanOrder(order_id, part_type, qty, priority, due)


def _integer(text: str, column: str, where: str) -> int:
    if re.fullmatch(r"[+-]?[0-9]{1,12}", text) is None:
        raise UsageError(f"{where}: {column} must be a whole number, not {text[:40]!r}")
    return int(text)


def orders_csv(orders: tuple[PlanOrder, ...]) -> str:
    """``orders`` as an orders file (due times as local date and time)."""
    from datetime import datetime

    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow([*REQUIRED, *OPTIONAL])
    for o in orders:
        due = "" if o.due is None else datetime.fromtimestamp(o.due).isoformat(timespec="seconds")
        writer.writerow([o.order_id, o.part_type, o.qty, o.priority, due])
    return out.getvalue()
