"""The dashboard in a real browser asks the cell nothing while it is hidden (a background tab,
a locked screen), and catches up the moment it is shown again."""

from __future__ import annotations

import asyncio
import time
from typing import Any

from tests.conftest import IN_BROWSER, SEEN_MS
from tests.test_dashboard import Dash, dash, live  # noqa: F401 (the fixture)

# On the session's event loop, where the browser lives (tests/conftest.py).
pytestmark = IN_BROWSER

#: What the page reads by itself now and then: the Gantt chart's steps, the traffic pane,
#: the status (figures that move with the clock alone), the audit trail, the shift's report.
READS = {"steps.list", "traffic.tail", "status", "audit.list", "report.shift"}
#: Longer than the longest of those periods but the shift's (10 s): each would have read.
#: (Reads not made are seen by time passing: there is no event to wait for.)
HIDDEN_S = 3.5
#: Shorter than the shift report's period (10 s): a page that reads it within this of being
#: shown read it at once, not on its next period (a bound, not a timing figure).
AT_ONCE_S = 8.0

# What the browser does when its tab goes to the background: the page's own code sees
# document.hidden change and a visibilitychange event.
SET_HIDDEN = """(hidden) => {
  Object.defineProperty(document, "hidden", { configurable: true, get: () => hidden });
  document.dispatchEvent(new Event("visibilitychange"));
}"""


def _read(request: Any) -> str | None:
    """What ``request`` of the page reads (an API method, or "status"), None for other."""
    if request.url.endswith("/api/status"):
        return "status"
    if request.url.endswith("/dashboard/call"):
        body = request.post_data_json or {}
        return str(body.get("method"))
    return None


async def test_a_hidden_page_reads_nothing_and_reads_at_once_when_shown(
    dash: Dash,  # noqa: F811
) -> None:
    page = dash.page
    seen: list[str] = []
    page.on("request", lambda r: seen.append(m) if (m := _read(r)) else None)
    await live(dash)
    await page.evaluate(SET_HIDDEN, True)
    seen.clear()
    # A change the page would show: it still comes by the live subscription.
    dash.rig.post("wax-robot-base", 1, "H1")
    await asyncio.sleep(HIDDEN_S)
    assert not READS & set(seen), f"a hidden page read {sorted(set(seen))}"
    await page.evaluate(SET_HIDDEN, False)
    deadline = time.monotonic() + AT_ONCE_S
    while not set(seen) >= READS:
        assert time.monotonic() < deadline, f"shown again, the page read only {set(seen)}"
        await asyncio.sleep(0.05)
    await page.locator("#order-table tr", has_text="H1").wait_for(timeout=SEEN_MS)
