"""The dashboard's What-if panel in a real browser: a plan of the running cell (the API's
plan.run) with a fault window and an order added from its form, its orders and chart shown;
a fault on a machine the cell does not have is refused with the cell's own message; a poll
period out of range is refused by the page in the console's words, the last refusal gone."""

from __future__ import annotations

import pytest

from cellctl.errors import UsageError
from cellctl.plan.when import parse_poll
from tests.conftest import IN_BROWSER
from tests.test_dashboard import Dash, dash, live  # noqa: F401 (the fixture)

# On the session's event loop, where the browser lives (tests/conftest.py).
pytestmark = IN_BROWSER


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
async def test_the_what_if_panel_plays_the_cell_ahead(dash: Dash) -> None:  # noqa: F811
    rig = dash.rig
    await live(dash)
    await dash.api("cell.pause")  # the orders stay open: the plan plays them
    rig.post("wax-robot-base", 1, "W1")
    await rig.wait_for(lambda: rig.order_state("W1") == "accepted", "W1 accepted")
    page = dash.page
    await page.locator("#plan-shift").fill("5m")
    await page.locator("#plan-fault").fill("cnc9:down@10:00-11:00")
    await page.locator("#plan-play").click()
    refused = page.locator("#plan-message", has_text="no such machine")
    await refused.wait_for(timeout=15_000)
    assert "cnc9" in await refused.inner_text()

    await page.locator("#plan-fault").fill("")
    await page.locator("#plan-add").fill("wax-toy-mill-table:1")
    await page.locator("#plan-policy").select_option("one-at-a-time")
    await page.locator("#plan-poll").fill("2")
    await page.locator("#plan-play").click()
    # Played: the orders' rows, or the plan's refusal in the panel's message.
    await page.wait_for_function(
        "() => document.querySelector('#plan-orders tr') !== null || "
        "!document.querySelector('#plan-message').textContent.startsWith('playing')",
        timeout=120_000,
    )
    assert await page.locator("#plan-message").inner_text() == ""
    rows = page.locator("#plan-orders tr")
    found = {
        (await r.get_attribute("data-policy"), await r.get_attribute("data-order"))
        for r in await rows.all()
    }
    assert found == {("one-at-a-time", "W1"), ("one-at-a-time", "plan-add1")}
    assert (await page.locator("#plan-window").inner_text()).endswith("(0:05:00), poll 2 s")
    # The same plan through the API: the same orders made, per policy.
    answer = await dash.api(
        "plan.run",
        {"shift": "5m", "add": ["wax-toy-mill-table:1"], "policy": "one-at-a-time", "poll": 2},
    )
    for plan in answer["plan"]["plans"]:
        for o in plan["orders"]:
            row = page.locator(
                f'#plan-orders tr[data-policy="{plan["policy"]}"][data-order="{o["order_id"]}"]'
            )
            cells = await row.locator("td").all_inner_texts()
            assert cells[3] == f"{o['made']}/{o['qty']}"
    chart = page.locator("#plan-chart")
    assert await chart.is_visible()
    assert await chart.evaluate("img => img.naturalWidth") > 0
    await dash.shot("what-if", "#plan")


def console_words(poll: str) -> str:
    """What the console (and the engine) say of a poll period typed as ``poll``."""
    with pytest.raises(UsageError) as refused:
        parse_poll(poll)
    return str(refused.value)


async def test_a_poll_out_of_range_is_told_in_the_console_s_words(dash: Dash) -> None:  # noqa: F811
    await live(dash)
    page = dash.page
    message = page.locator("#plan-message")
    await page.locator("#plan-shift").fill("5m")
    await page.locator("#plan-add").fill("wax-toy-mill-table:1")
    await page.locator("#plan-fault").fill("cnc9:down@10:00-11:00")
    await page.locator("#plan-play").click()
    await page.locator("#plan-message", has_text="no such machine").wait_for(timeout=15_000)

    # The browser's own check would stop Play with a bubble a headless browser never shows,
    # and leave cnc9's refusal standing: the page tells it, in place of the last words.
    await page.locator("#plan-fault").fill("")
    await page.locator("#plan-poll").fill("0")
    await page.locator("#plan-play").click()
    told = page.locator("#plan-message", has_text="poll")
    await told.wait_for(timeout=15_000)
    assert await told.inner_text() == "poll '0': seconds, more than 0 and at most 600"
    assert await told.inner_text() == console_words("0")
    for typed in ("600.5", "-1", "1e3", "five", "nan"):
        await page.locator("#plan-poll").fill(typed)
        await page.locator("#plan-play").click()
        await page.locator("#plan-message", has_text=repr(typed)).wait_for(timeout=15_000)
        assert await message.inner_text() == console_words(typed)
    assert await page.locator("#plan-orders tr").count() == 0  # nothing was played
    assert await page.locator("#plan-play").is_enabled()


async def test_the_what_if_form_says_the_plans_own_default_poll() -> None:
    """The page's poll field shows the plan's default as cellctl plan takes it (it said 5 s
    when the default was 15 s)."""
    import re
    from importlib.resources import files

    from cellctl.plan.when import PLAN_POLL_S

    page = files("cellctl.ui.dashboard").joinpath("static/index.html").read_text()
    field = re.search(
        r'<label title="([^"]*)">poll <input id="plan-poll"[^>]*placeholder="([^"]*)"', page
    )
    assert field is not None
    assert field.group(2) == f"{PLAN_POLL_S:g}"
    assert f"the plan's {PLAN_POLL_S:g} s" in field.group(1)
