"""The dashboard's orders in a real browser (Debian's Chromium through Playwright) against the
emulated cell and the real controller: each order's due time in its own column, local and
short, LATE in words beside one past it, and an order that passes its due time while the page
is open turning LATE by itself (pushed, the page not reloaded)."""

from __future__ import annotations

import time

from tests.conftest import IN_BROWSER, SEEN_MS
from tests.test_dashboard import Dash, dash, live  # noqa: F401 (the fixture)
from tests.test_due_live import ahead, backlog, shown, submit

# On the session's event loop, where the browser lives (tests/conftest.py).
pytestmark = IN_BROWSER


async def test_the_orders_show_their_due_times_and_late(dash: Dash) -> None:  # noqa: F811
    await dash.api("cell.pause")  # the orders stay open, as they are put
    past_text, past = backlog()
    later = ahead()
    for oid, due in [("P1", past_text), ("A1", later), ("N1", None)]:
        await dash.api("orders.submit", submit(oid, due))
    await live(dash)
    page = dash.page
    table = page.locator("#order-table")
    heads = await table.locator("thead th").all_inner_texts()
    rows = table.locator("tbody tr")
    await rows.nth(2).wait_for(timeout=SEEN_MS)

    async def due_of(oid: str) -> str:
        row = table.locator(f'tbody tr[data-order="{oid}"]')
        return (await row.locator("td").nth(heads.index("due")).inner_text()).strip()

    assert await due_of("P1") == f"{shown(past)} LATE"
    assert await due_of("A1") == shown(later)
    assert await due_of("N1") == "—"
    await dash.shot("orders-due", "#orders")

    # Due in two seconds: shown due, then LATE as its time passes, with nothing else changing.
    soon = time.time() + 2.0
    await dash.api("orders.submit", submit("S1", soon))
    late = table.locator('tbody tr[data-order="S1"] td.due.late', has_text="LATE")
    await late.wait_for(timeout=SEEN_MS)
    assert (await late.inner_text()).startswith(shown(soon))
