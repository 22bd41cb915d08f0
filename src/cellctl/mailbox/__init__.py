"""Where orders come in and reports go out.

::

    from cellctl.mailbox import ReportKind, open_mailbox

    with open_mailbox(cell_dir) as mailbox:          # <cell_dir>/mailbox.sqlite3
        order, new = mailbox.post_order("wax-robot", qty=2, order_id="A17")
        for order in mailbox.pending_orders():
            mailbox.set_order_state(order.id, "accepted")
            mailbox.post_report(ReportKind.ORDER_ACCEPTED, f"order {order.id} accepted",
                                order_id=order.id)

Order states: ``posted -> accepted -> in-progress -> done | failed | cancelled``, and
``held`` while one of the order's parts waits for the operator (see ``TRANSITIONS``).
"""

from __future__ import annotations

from pathlib import Path

from cellctl.errors import UsageError
from cellctl.mailbox.base import (
    ACCEPTED,
    CANCELLED,
    DONE,
    FAILED,
    FINAL_STATES,
    HELD,
    IN_PROGRESS,
    ORDER_STATES,
    POSTED,
    REPORT_KINDS,
    TRANSITIONS,
    Mailbox,
    Order,
    Report,
    ReportKind,
)
from cellctl.mailbox.sqlite import SqliteMailbox

__all__ = [
    "ACCEPTED",
    "CANCELLED",
    "DONE",
    "FAILED",
    "FINAL_STATES",
    "HELD",
    "IN_PROGRESS",
    "MAILBOX_FILE",
    "ORDER_STATES",
    "POSTED",
    "REPORT_KINDS",
    "TRANSITIONS",
    "Mailbox",
    "Order",
    "Report",
    "ReportKind",
    "SqliteMailbox",
    "open_mailbox",
]

#: The default mailbox's file name inside the cell directory.
MAILBOX_FILE = "mailbox.sqlite3"


def open_mailbox(cell_dir: Path, url: str | None = None) -> Mailbox:
    """Open the cell's mailbox.

    ``url`` None or ``sqlite`` means ``<cell_dir>/mailbox.sqlite3``; ``sqlite:PATH`` (or
    ``sqlite:///abs/path``) names another file. Any other scheme is refused.
    """
    if url is None or url == "sqlite":
        return SqliteMailbox(Path(cell_dir) / MAILBOX_FILE)
    scheme, sep, rest = url.partition(":")
    if not sep or scheme != "sqlite":
        raise UsageError(f"no such mailbox backend: {url!r} (known: sqlite)")
    if rest.startswith("//"):
        rest = rest[2:]
    if not rest:
        return SqliteMailbox(Path(cell_dir) / MAILBOX_FILE)
    return SqliteMailbox(Path(rest))
