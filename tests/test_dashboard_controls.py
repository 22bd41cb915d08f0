"""The dashboard's controls and its look, in a real Chromium against the emulated cell and the
real controller: pause, resume, E-stop with a reason, a machine out of and back in service
with a reason (confirmed where work stops, refusals in the API's words, a wrong token), and
finding 14 (24-hour clock, the floor's panel, toolpath text, step names, a cutting mill's
utilization, the favicon, the connecting state)."""

from __future__ import annotations

import asyncio
import re
import time
from typing import Any

import pytest
from playwright.async_api import Page, Request, Response, Route

from cellctl.service.token import add_token
from tests import test_dashboard
from tests.conftest import IN_BROWSER, SEEN_MS
from tests.test_dashboard import Dash, http, live

# On the session's event loop, where the browser lives (tests/conftest.py).
pytestmark = IN_BROWSER

# The cell with its dashboard, as tests/test_dashboard.py starts it.
dash = test_dashboard.dash

CONTROLS = "#cell-controls"


async def mode(dash: Dash) -> str:
    return str((await dash.api("cell.status"))["cell"]["mode"])


async def test_pause_resume_and_an_emergency_stop_with_a_reason(dash: Dash) -> None:
    await live(dash)
    page = dash.page
    pause = page.locator(f'{CONTROLS} button[data-method="cell.pause"]')
    resume = page.locator(f'{CONTROLS} button[data-method="cell.resume"]')
    estop = page.locator(f'{CONTROLS} button[data-method="cell.estop"]')
    await pause.wait_for(timeout=SEEN_MS)
    assert await resume.is_disabled()  # running: there is nothing to resume
    # Pausing stops work: confirmed first, and a "Cancel" leaves the cell as it was.
    await pause.click()
    assert "Pause the cell" in await page.locator("#confirm-text").inner_text()
    await page.locator("#confirm-no").click()
    assert await mode(dash) == "running"
    await pause.click()
    await dash.confirm()
    await page.locator("#cell-state.mode-paused").wait_for(timeout=SEEN_MS)
    assert await mode(dash) == "paused"
    message = page.locator("#control-message.ok")
    await message.wait_for(timeout=SEEN_MS)
    assert "paused" in await message.inner_text()
    assert await pause.is_disabled()
    # Resuming stops nothing: no confirmation.
    await resume.click()
    await page.locator("#cell-state.mode-running").wait_for(timeout=SEEN_MS)
    assert await mode(dash) == "running"
    # A reason longer than the API takes: refused in its words, the cell not stopped.
    await estop.click()
    await page.locator("#confirm-reason").fill("y" * 501)
    await dash.confirm()
    refusal = page.locator("#control-message.error")
    await refusal.wait_for(timeout=SEEN_MS)
    assert "500 characters" in await refusal.inner_text()
    assert await mode(dash) == "running"
    # The emergency stop asks first, with a reason that goes into the alarm and the journal.
    await estop.click()
    assert "EMERGENCY STOP" in await page.locator("#confirm-text").inner_text()
    await page.locator("#confirm-reason").fill("guard door open")
    await dash.shot("estop-confirm")
    await dash.confirm()
    await page.locator("#cell-state.mode-emergency-stop").wait_for(timeout=SEEN_MS)
    row = page.locator("#alarm-table tbody tr[data-alarm]", has_text="guard door open")
    await row.wait_for(timeout=SEEN_MS)
    assert "emergency stop: guard door open" in await row.inner_text()
    await page.locator("#control-message.ok", has_text="guard door open").wait_for(timeout=SEEN_MS)
    alarms = await dash.api("alarms.list")
    assert any(a["text"] == "emergency stop: guard door open" for a in alarms), alarms
    await dash.shot("estop", CONTROLS)
    # It stays stopped until its alarm is cleared; then it is paused, and Resume runs it.
    assert await resume.is_disabled()
    await row.locator('button[data-method="alarms.clear"]').click()
    await dash.confirm()
    await page.locator("#cell-state.mode-paused").wait_for(timeout=SEEN_MS)
    await resume.click()
    await page.locator("#cell-state.mode-running").wait_for(timeout=SEEN_MS)
    assert await mode(dash) == "running"


async def test_a_machine_out_of_service_and_back_from_its_card(dash: Dash) -> None:
    await live(dash)
    page = dash.page
    card = page.locator('#machine-cards .card[data-machine="cnc2"]')
    out = card.locator('button[data-method="machines.out_of_service"]')
    back = card.locator('button[data-method="machines.return_to_service"]')
    await out.wait_for(timeout=SEEN_MS)
    assert await back.is_hidden()
    # Out of service stops work on the machine: confirmed, with a reason it will not go without.
    await out.click()
    assert "Take cnc2 out of automatic service" in await page.locator("#confirm-text").inner_text()
    await dash.confirm()
    assert await page.locator("#confirm").is_visible(), "confirmed without a reason"
    assert await page.locator("#confirm-reason:invalid").count() == 1
    # A reason longer than the API takes: refused in the API's words, nothing changed.
    await page.locator("#confirm-reason").fill("x" * 600)
    await dash.confirm()
    refusal = card.locator(".control-message.error")
    await refusal.wait_for(timeout=SEEN_MS)
    assert "reason" in (text := await refusal.inner_text()) and "500 characters" in text, text
    assert (await dash.api("machines.list"))["cnc2"]["in_service"] is True
    await out.click()
    await page.locator("#confirm-reason").fill("new cutter")
    await dash.confirm()
    await page.locator('.card.condition-out-of-service[data-machine="cnc2"]').wait_for(
        timeout=SEEN_MS
    )
    assert "new cutter" in await card.locator(".machine-state").inner_text()
    assert "out of automatic service" in await card.locator(".control-message.ok").inner_text()
    status = (await dash.api("machines.list"))["cnc2"]
    assert status["in_service"] is False and "new cutter" in status["out_reason"]
    assert await out.is_hidden()
    await dash.shot("machine-out", "#machines")
    # Back in service starts nothing by itself: no confirmation.
    await back.click()
    await page.locator('.card.condition-idle[data-machine="cnc2"]').wait_for(timeout=SEEN_MS)
    assert (await dash.api("machines.list"))["cnc2"]["in_service"] is True
    assert "back in automatic service" in await card.locator(".control-message.ok").inner_text()


async def test_a_wrong_token_gets_no_controls_and_changes_nothing(dash: Dash) -> None:
    await dash.open("#token=wrong-token")
    page = dash.page
    await page.locator("#refused").wait_for(state="visible", timeout=SEEN_MS)
    assert await page.locator(CONTROLS).is_hidden()
    assert await page.locator("[data-method]:visible").count() == 0
    assert await page.locator("#connecting").is_hidden()
    calls = [
        ("cell.pause", {}),
        ("cell.resume", {}),
        ("cell.estop", {"reason": "from a wrong token"}),
        ("machines.out_of_service", {"machine": "cnc1", "reason": "from a wrong token"}),
        ("machines.return_to_service", {"machine": "cnc1"}),
    ]
    for method, params in calls:
        status, body = await http(
            dash.base + "/dashboard/call",
            token="wrong-token",
            body={"method": method, "params": params},
        )
        assert status == 401 and "result" not in body, method
        assert "token" in body["error"]["message"]
    assert await mode(dash) == "running"
    assert (await dash.api("machines.list"))["cnc1"]["in_service"] is True
    assert await dash.api("alarms.list") == []


async def test_a_viewer_is_refused_the_controls_in_words(dash: Dash) -> None:
    viewer = add_token(dash.rig.directory, "vic", "viewer")
    await dash.open(f"#token={viewer}")
    page = dash.page
    await page.locator("#connection.good").wait_for(timeout=SEEN_MS)
    await page.locator(f'{CONTROLS} button[data-method="cell.estop"]').click()
    await page.locator("#confirm-reason").fill("a viewer tries")
    await dash.confirm()
    refusal = page.locator("#control-message.error")
    await refusal.wait_for(timeout=SEEN_MS)
    assert "vic is a viewer: cell.estop needs the operator role" in await refusal.inner_text()
    card = page.locator('#machine-cards .card[data-machine="cnc1"]')
    await card.locator('button[data-method="machines.out_of_service"]').click()
    await page.locator("#confirm-reason").fill("a viewer tries")
    await dash.confirm()
    out = card.locator(".control-message.error")
    await out.wait_for(timeout=SEEN_MS)
    assert "needs the operator role" in await out.inner_text()
    assert await mode(dash) == "running"
    assert (await dash.api("machines.list"))["cnc1"]["in_service"] is True


# -- finding 14 ---------------------------------------------------------------------------------


async def test_times_are_on_the_24_hour_clock(dash: Dash) -> None:
    # A locale whose own clock has 12 hours: the page keeps to 24.
    context = await dash.page.context.browser.new_context(locale="en-US")  # type: ignore[union-attr]
    try:
        dash.page = await context.new_page()
        await live(dash)
        assert await dash.page.evaluate("new Date(2000, 0, 1, 20).toLocaleTimeString()") == (
            "8:00:00 PM"
        )
        await dash.api("machines.out_of_service", {"machine": "cnc1", "reason": "clock check"})
        item = dash.page.locator("#event-list li", has_text="clock check")
        await item.wait_for(timeout=SEEN_MS)
        shown = await item.locator("time").inner_text()
        assert re.fullmatch(r"\d\d:\d\d:\d\d", shown), shown
        text = await dash.page.locator("body").inner_text()
        assert not re.search(r"\d (AM|PM)\b", text), text
        await dash.api("machines.return_to_service", {"machine": "cnc1"})
    finally:
        await context.close()


async def test_the_page_while_connecting_says_so(dash: Dash) -> None:
    held = asyncio.Event()
    go = asyncio.Event()

    async def hold(route: Route) -> None:
        held.set()
        await go.wait()
        await route.continue_()

    page = dash.page
    await page.route("**/access/oneshot_token", hold)
    await dash.page.goto("about:blank")
    opened = asyncio.create_task(page.goto(f"{dash.base}/#token={dash.token}"))
    async with asyncio.timeout(10):
        await held.wait()
    waiting = page.locator("#connecting")
    await waiting.wait_for(state="visible", timeout=SEEN_MS)
    assert "Connecting to the cell's controller" in await waiting.inner_text()
    assert "connecting" in await page.locator("#connection").inner_text()
    assert await page.locator("#content").is_hidden()
    await dash.shot("connecting")
    go.set()
    await opened
    await page.locator("#connection.good").wait_for(timeout=SEEN_MS)
    assert await waiting.is_hidden()
    await page.unroute("**/access/oneshot_token")


@pytest.mark.parametrize("dash", [200.0], indirect=True)  # cuts of a few seconds
async def test_a_batch_reads_well(dash: Dash) -> None:
    """With two mills cutting: the floor's panel holds no half-empty page, the toolpath's
    text is readable, step names keep their words whole, a cutting mill is busy (not 0 %),
    and nothing the page asks for is missing (the favicon)."""
    page = dash.page
    missing: list[str] = []

    def seen(response: Response) -> None:
        if response.status == 404:
            missing.append(response.url)

    def failed(request: Request) -> None:
        missing.append(f"{request.url} ({request.failure})")

    page.on("response", seen)
    page.on("requestfailed", failed)
    await live(dash)
    dash.rig.post("wax-toy-mill-table", 3, "B1")  # the longest program names
    # A mill whose first cut has run for a while, with its drawing on its card.
    cutting = None
    deadline = time.monotonic() + 60
    while cutting is None and time.monotonic() < deadline:
        dash.rig.check_running()
        status = await dash.api("cell.status")
        for name, m in status["machines"].items():
            step = m["step"]
            if (
                m["family"] == "mill"
                and step
                and step["what"] == "machine"
                and status["cell"]["time"] - step["started"] > 0.5
            ):
                cutting = name
        await asyncio.sleep(0.05)
    assert cutting is not None, f"no mill cut for 0.5 s\n{dash.rig.describe()}"
    # Busy while it cuts: the step in flight counts (it was "0.0 % busy" until the first cut
    # ended), in the status and on its card.
    machine = status["machines"][cutting]
    assert machine["busy_s"] >= 0.5 and machine["utilization"] > 0, machine
    await page.wait_for_function(
        """(name) => {
          const card = document.querySelector(`.card[data-machine="${name}"]`);
          const shown = card.querySelector('.utilization').textContent;
          return card.dataset.condition === 'busy' && parseFloat(shown) > 0;
        }""",
        arg=cutting,
        timeout=30_000,
    )

    # Each look below is taken in one go in the page, at a moment a mill's card shows its
    # cut (the batch's cuts follow one another; a look waits for the next one if need be).
    # The floor's panel ends near its legend: not stretched to the machines' column.
    blank = await while_cutting(page, FLOOR_BLANK)
    assert blank < 0.1, f"{blank:.0%} of the floor's panel is blank"
    # A mill's texts on the floor (its step and program's name) stay inside its box.
    out = await while_cutting(page, FLOOR_TEXT_OUT)
    assert not out, f"texts running out of their mill's box on the floor: {out}"
    # Every text of the drawing on the card is at least 10 px high (the drawing's own labels
    # are left to the full-size view), and its caption is the page's text.
    small, caption, size = await while_cutting(page, PREVIEW_TEXT)
    assert all(h >= 10 for h in small), small
    assert "block" in caption and size >= 10, (caption, size)
    full = page.locator("#toolpath-view")
    await full.locator("svg").wait_for(timeout=SEEN_MS)
    heights = await full.evaluate(TEXT_HEIGHTS)
    assert heights and min(heights) >= 10, heights
    await dash.shot("toolpath")
    await page.locator("#toolpath-close").click()
    # A step's name breaks between its words only (at a space, or after a "_" of a program's
    # name) and stays in its card, on a laptop and on a tablet.
    for width in (1400, 1180, 820):
        await page.set_viewport_size({"width": width, "height": 1000})
        shown, broken, inside = await while_cutting(page, STEP_WORDS)
        assert not broken, f"words broken at {width} px: {broken} ({shown!r})"
        assert inside, f"the step's name runs out of its card at {width} px: {shown!r}"
    await dash.shot("batch")
    icon, kind = await asyncio.to_thread(_get, dash.base + "/favicon.ico")
    assert icon == 200 and kind.startswith("image/svg+xml")
    assert not missing, f"the page asked for what is not there: {missing}"


async def test_a_tall_machine_column_stretches_no_panel_beside_it(dash: Dash) -> None:
    """More machines than the lab's two mills (their cards taller than the floor, the orders
    and the alarms together): the floor's and the orders' panels keep their own height, and
    the floor's ends near its legend."""
    page = dash.page
    await live(dash)
    heights = """() => ['#floor', '#orders'].map(
      (id) => Math.round(document.querySelector(id).getBoundingClientRect().height))"""
    before = await page.evaluate(heights)
    await page.evaluate(
        """() => {
          const filler = document.createElement('div');
          filler.style.height = '700px';
          document.querySelector('#machines').appendChild(filler);
        }"""
    )
    assert await page.evaluate(heights) == before
    blank = await page.evaluate(FLOOR_BLANK)
    assert blank < 0.1, f"{blank:.0%} of the floor's panel is blank"
    await dash.shot("tall-column")


def _get(url: str) -> tuple[int, str]:
    import urllib.request

    with urllib.request.urlopen(url, timeout=5) as answer:
        return answer.status, answer.headers["Content-Type"]


#: The rendered heights (px) of the visible texts of an SVG in an element.
TEXT_HEIGHTS = """(box) => [...box.querySelectorAll('svg text')]
  .map((t) => t.getBoundingClientRect())
  .filter((r) => r.width > 0 && r.height > 0)
  .map((r) => r.height)"""


async def while_cutting(page: Page, look: str) -> Any:
    """``look`` (a function of the card of a mill that shows a toy table's cut, in the page)
    taken at a moment such a card is shown: what it returns."""
    found = await page.wait_for_function(
        f"""() => {{
          const card = [...document.querySelectorAll('.card.condition-busy')].find((c) =>
            c.querySelector('.step').textContent.includes('toy_mill_table')
            && c.querySelector('.preview svg') && c.querySelector('.preview').offsetParent);
          return card ? [({look})(card)] : null;
        }}""",
        timeout=30_000,
    )
    return (await found.json_value())[0]


#: How much of the floor's panel is blank below its legend.
FLOOR_BLANK = """() => {
  const panel = document.querySelector('#floor').getBoundingClientRect();
  const legend = document.querySelector('#floor .legend').getBoundingClientRect();
  return (panel.bottom - legend.bottom) / panel.height;
}"""

#: The floor's texts that run out of their mill's box.
FLOOR_TEXT_OUT = """() => [...document.querySelectorAll('#floor-plan .machine.mill')]
  .flatMap((g) => {
    const box = g.querySelector('.body').getBoundingClientRect();
    return [...g.querySelectorAll('.status, .status-program')]
      .filter((t) => t.getBoundingClientRect().right > box.right)
      .map((t) => t.textContent);
  })"""

#: The card's drawing: its visible texts' heights, its caption and the caption's size; then
#: a click on the drawing (its full-size view opens).
PREVIEW_TEXT = """(card) => {
  const heights = TEXT_HEIGHTS(card.querySelector('.preview'));
  const caption = card.querySelector('.preview-caption');
  const size = parseFloat(getComputedStyle(caption).fontSize);
  card.querySelector('.preview svg').dispatchEvent(new MouseEvent('click', { bubbles: true }));
  return [heights, caption.textContent, size];
}""".replace("TEXT_HEIGHTS", f"({TEXT_HEIGHTS})")

#: The words (runs between spaces and after "_") of an element's text laid out over more than
#: one line.
BROKEN_WORDS = """(node) => {
  const out = [];
  const walker = document.createTreeWalker(node, NodeFilter.SHOW_TEXT);
  for (let text = walker.nextNode(); text; text = walker.nextNode()) {
    for (const m of text.textContent.matchAll(/[^ _]+_?/g)) {
      const range = document.createRange();
      range.setStart(text, m.index);
      range.setEnd(text, m.index + m[0].length);
      const tops = new Set([...range.getClientRects()].map((r) => Math.round(r.top)));
      if (tops.size > 1) out.push(m[0]);
    }
  }
  return out;
}"""

#: The card's step: its text, its words laid out over two lines, whether it stays inside.
STEP_WORDS = f"""(card) => {{
  const step = card.querySelector('.step');
  return [step.textContent, ({BROKEN_WORDS})(step),
    step.getBoundingClientRect().right <= card.getBoundingClientRect().right];
}}"""
