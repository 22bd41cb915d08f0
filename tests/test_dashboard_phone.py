"""The dashboard on a phone (380 px wide) in a real browser: the page never scrolls sideways;
a table wider than the screen (held parts, the shift's figures, the audit trail) scrolls
inside its own box, its every column still there to scroll to."""

from __future__ import annotations

from tests.conftest import IN_BROWSER, SEEN_MS
from tests.test_dashboard import Dash, dash, live  # noqa: F401 (the fixture)

# On the session's event loop, where the browser lives (tests/conftest.py).
pytestmark = IN_BROWSER

PHONE = {"width": 380, "height": 800}
TABLES = ("#held-table", "#shift-table", "#audit-table")

# What sticks out of the screen on the right: the elements whose right edge passes it, not
# counting those inside a box that scrolls or clips them (the Gantt chart's, a table's).
STICKING_OUT = """() => {
  const clipped = (e) => {
    for (let a = e.parentElement; a && a !== document.body; a = a.parentElement) {
      if (getComputedStyle(a).overflowX !== 'visible') return true;
    }
    return false;
  };
  return [...document.querySelectorAll('body *')]
    .filter((e) => e.getBoundingClientRect().right > window.innerWidth + 0.5 && !clipped(e))
    .map((e) => e.id ? '#' + e.id : e.tagName.toLowerCase());
}"""

# A table's box: whether it scrolls sideways, stays on the screen, and holds the whole table.
TABLE_BOX = """(table) => {
  const box = table.parentElement;
  const r = box.getBoundingClientRect();
  box.scrollLeft = box.scrollWidth;
  return {
    overflow: getComputedStyle(box).overflowX,
    inside: r.left >= 0 && r.right <= window.innerWidth + 0.5,
    wider: table.scrollWidth > box.clientWidth,
    whole: box.scrollWidth >= table.getBoundingClientRect().width - 0.5,
    scrolled: box.scrollLeft > 0,
  };
}"""


async def test_on_a_phone_wide_tables_scroll_in_their_boxes_not_the_page(
    dash: Dash,  # noqa: F811
) -> None:
    rig = dash.rig
    # Rows as a shift leaves them: audited calls with the API's long method names, a held
    # part whose note names a program file.
    await dash.api("cell.pause")
    await dash.api("machines.out_of_service", {"machine": "cnc1", "reason": "spindle check"})
    await dash.api("machines.return_to_service", {"machine": "cnc1"})
    rig.post("wax-toy-mill-table", 1, "P1")
    parts = await rig.wait_for(lambda: rig.journal.parts(order_id="P1"), "P1's parts")
    for part in parts:
        rig.journal.hold_part(part.id, "chipped: see programs/toy_mill_table_finish_cnc2.dyn")
    rig.controller.poke()  # type: ignore[union-attr]
    page = dash.page
    await page.set_viewport_size(PHONE)
    await live(dash)
    await page.locator(f'#held-table tr[data-part="{parts[0].id}"]').wait_for(timeout=SEEN_MS)
    await page.locator("#shift-machines tr").first.wait_for(timeout=SEEN_MS)
    audited = page.locator("#audit-table tbody tr", has_text="return_to_service")
    await audited.wait_for(timeout=SEEN_MS)

    wider = await page.evaluate("document.documentElement.scrollWidth - window.innerWidth")
    out = await page.evaluate(STICKING_OUT)
    assert wider <= 0 and not out, f"the page is {wider} px wider than a phone: {out}"
    for selector in TABLES:
        box = await page.locator(selector).evaluate(TABLE_BOX)
        assert box["overflow"] in ("auto", "scroll"), (selector, box)
        assert box["inside"] and box["whole"], (selector, box)
        # Wider than the phone: its last column is there, scrolled to inside the box.
        assert not box["wider"] or box["scrolled"], (selector, box)
    await dash.shot("phone")
