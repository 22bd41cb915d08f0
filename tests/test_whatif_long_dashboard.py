"""The dashboard's What-if panel waits for a plan as ``cellctl plan`` does (docs/plan.md), in a
real browser: while its play tells how far it has gone, past the silence allowed, how far
shown in the panel; a plan that goes silent is given up in the command line's words, and its
play ends (the page's own WebSocket for it closed).

The silence allowed is the form's ``data-silence`` (the command line's 600 s in the page as
shipped), set short here; a plan goes silent as a stuck one does: its play's worker process
stopped (tests/test_whatif_long_console.py, ``plays_stuck``).
"""

from __future__ import annotations

import re
from importlib.resources import files

import pytest

from cellctl.service.client import PLAN_SILENCE_S
from tests.conftest import IN_BROWSER
from tests.test_dashboard import Dash, dash, live  # noqa: F401 (the fixture)
from tests.test_whatif_long_console import (
    GUARD_S,
    HEARD_SILENCE_S,
    SHORT,
    SILENCE_S,
    plays_stuck,
    worker_ended,
)

GUARD_MS = int(GUARD_S * 1000)


async def ask_plan(dash: Dash, silence_s: float) -> None:  # noqa: F811
    """The panel's form filled for a plan of some seconds, allowed ``silence_s``; Play."""
    page = dash.page
    await page.locator("#plan-form").evaluate(
        "(form, s) => { form.dataset.silence = s; }", f"{silence_s:g}"
    )
    await page.locator("#plan-shift").fill("6h")
    await page.locator("#plan-add").fill("wax-robot-base:8")
    await page.locator("#plan-poll").fill("2")
    await page.locator("#plan-play").click()


@IN_BROWSER  # on the session's event loop, where the browser lives (tests/conftest.py)
@pytest.mark.timeout(300)  # the plan plays on a busy box: CPU, not waiting
async def test_a_plan_heard_from_is_answered_past_the_silence_allowed(dash: Dash) -> None:  # noqa: F811
    await live(dash)
    page = dash.page
    await ask_plan(dash, HEARD_SILENCE_S)
    # How far it has gone, in `cellctl plan`'s words, while it plays.
    told = page.locator("#plan-message", has_text=re.compile(r"^playing: .* of 6:00:00 machine"))
    await told.wait_for(timeout=GUARD_MS)
    await page.locator("#plan-orders tr").first.wait_for(timeout=2 * GUARD_MS)
    assert await page.locator("#plan-message").inner_text() == ""
    orders = await page.locator("#plan-orders tr").evaluate_all(
        "rows => rows.map(r => r.dataset.order)"
    )
    assert "plan-add1" in orders
    assert await page.locator("#plan-play").is_enabled()


@IN_BROWSER
@pytest.mark.timeout(300)
async def test_a_silent_plan_is_given_up_in_words_and_its_play_ends(dash: Dash) -> None:  # noqa: F811
    await live(dash)
    page = dash.page
    async with plays_stuck():
        await ask_plan(dash, SILENCE_S)
        given_up = page.locator("#plan-message", has_text="nothing heard")
        await given_up.wait_for(timeout=GUARD_MS)
        # The command line's words (cellctl.service.client.plan_call's).
        assert await given_up.inner_text() == (
            f"plan.run: nothing heard of the plan for {SILENCE_S:g} s: it is stuck "
            "(the cell's log may say why)"
        )
        assert await page.locator("#plan-orders tr").count() == 0
        assert await page.locator("#plan-play").is_enabled()
        # The page closed the plan's socket: the API ended its play (its worker killed).
        await worker_ended()
    # The cell's one play is free: another plan is answered, not refused as playing.
    answer = await dash.api("plan.run", SHORT)
    assert answer["plan"]["plans"]


def test_the_page_allows_a_plan_the_command_lines_silence() -> None:
    """The page as shipped gives a plan up after the command line's silence, not sooner."""
    page = files("cellctl.ui.dashboard").joinpath("static/index.html").read_text()
    form = re.search(r'<form id="plan-form"[^>]*data-silence="([^"]*)"', page)
    assert form is not None
    assert float(form.group(1)) == PLAN_SILENCE_S
