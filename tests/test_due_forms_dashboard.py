"""The dashboard's order form with a due time, in a real browser (Debian's Chromium through
Playwright) against the emulated cell and the real controller: a due time the cell cannot
read is refused in the API's words (nothing posted, the field kept and selected); a weekday
and time posts the order due then, in the orders table; a time already past posts it LATE;
the What-if form shows how an added order takes a due time."""

from __future__ import annotations

import re

from tests.conftest import IN_BROWSER, SEEN_MS
from tests.test_dashboard import Dash, dash, live  # noqa: F401 (the fixture)
from tests.test_due_forms import weekday_ahead
from tests.test_due_live import backlog, shown

# On the session's event loop, where the browser lives (tests/conftest.py).
pytestmark = IN_BROWSER


async def test_the_order_form_takes_a_due_time(dash: Dash) -> None:  # noqa: F811
    await dash.api("cell.pause")  # the orders stay open, as they are put
    await live(dash)
    page = dash.page
    due_field = page.locator("#order-due")
    assert await due_field.get_attribute("placeholder") == "FRI 18:00"
    await page.select_option("#order-type", "wax-robot-base")

    # Refused in the API's words; nothing posted; the field kept, selected for the next keys.
    await due_field.fill("FRI 25:00")
    await page.click("#order-submit")
    refused = page.locator("#order-message.error")
    await refused.wait_for(timeout=SEEN_MS)
    text = await refused.inner_text()
    assert "due: time 'FRI 25:00': hours 0-23, minutes 0-59" in text, text
    assert await due_field.input_value() == "FRI 25:00"
    assert await page.evaluate("document.activeElement.id") == "order-due"
    assert await dash.api("orders.list") == []

    # A weekday and time: the next such time, in the message and the table's due column.
    text, due = weekday_ahead()
    await due_field.fill(text)
    await page.click("#order-submit")
    message = page.locator("#order-message.ok")
    await message.wait_for(timeout=SEEN_MS)
    assert "posted" in await message.inner_text()
    [order] = await dash.api("orders.list")
    assert (order["due"], order["late"]) == (due, False)
    table = page.locator("#order-table")
    heads = await table.locator("thead th").all_inner_texts()
    cell = table.locator(f'tbody tr[data-order="{order["id"]}"] td').nth(heads.index("due"))
    await cell.wait_for(timeout=SEEN_MS)
    assert (await cell.inner_text()).strip() == shown(due)

    # A time already past (a planner's backlog): taken, and LATE at once.
    past_text, past = backlog()
    await due_field.fill(past_text)
    await page.click("#order-submit")
    await page.locator("#order-message.ok", has_text="already past").wait_for(timeout=SEEN_MS)
    late = table.locator("tbody tr td.due.late", has_text="LATE")
    await late.wait_for(timeout=SEEN_MS)
    assert (await late.inner_text()).strip() == f"{shown(past)} LATE"
    await dash.shot("order-form-due", "#orders")

    # An order without a due time still goes as before (the field left empty).
    await due_field.fill("")
    await page.click("#order-submit")
    # Its message has no due time (the one before said "already past").
    posted = page.locator("#order-message.ok", has_text=re.compile(r"posted: .*priority 0$"))
    await posted.wait_for(timeout=SEEN_MS)
    orders = await dash.api("orders.list")
    assert sorted(o["due"] is None for o in orders) == [False, False, True]

    # The What-if form's orders to add show how one takes a due time.
    placeholder = await page.locator("#plan-add").get_attribute("placeholder")
    assert placeholder is not None and "PART:QTY[@PRIORITY][ by WHEN]" in placeholder
