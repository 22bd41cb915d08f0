"""The dashboard with a viewer's token: it reads the cell and the audit trail, and its order
is refused with the role it lacks, shown on the page and recorded in the Audit panel."""

from __future__ import annotations

import re

from cellctl.service.token import add_token
from tests.conftest import IN_BROWSER
from tests.test_dashboard import Dash, dash, live  # noqa: F401  (the fixture)

# On the session's event loop, where the browser lives (tests/conftest.py).
pytestmark = IN_BROWSER


async def test_a_viewer_reads_the_page_is_refused_an_order_and_sees_it_audited(
    dash: Dash,  # noqa: F811
) -> None:
    await dash.api("cell.pause")
    viewer = add_token(dash.rig.directory, "vera", "viewer")
    await dash.open(f"#token={viewer}")
    page = dash.page
    await page.locator("#connection.good").wait_for(timeout=10_000)
    await page.locator("#floor-plan svg .machine.mill").first.wait_for(timeout=5_000)
    await page.select_option("#order-type", "wax-toy-mill-table")
    await page.click("#order-submit")
    refused = page.locator("#order-message.error")
    await refused.wait_for(timeout=5_000)
    assert "vera is a viewer: orders.submit needs the operator role" in await refused.inner_text()
    assert await dash.api("orders.list") == []
    row = page.locator("#audit-table tbody tr.audit-refused", has_text="token:vera")
    await row.wait_for(timeout=10_000)
    text = await row.inner_text()
    assert "orders.submit" in text and "wax-toy-mill-table" in text
    assert "needs the operator role" in text
    # The engineer's pause (the local user, in-process) is there too, as done.
    done = page.locator("#audit-table tbody tr.audit-ok", has_text="cell.pause")
    assert await done.count() == 1
    # How long it took, as `cellctl audit` says it; a refusal took no time of its own.
    cells = await done.locator("td").all_inner_texts()
    assert re.fullmatch(r"\d+\.\d s", cells[1]), cells
    assert (await row.locator("td").all_inner_texts())[1] == "", text
    await dash.shot("audit", "#audit")
