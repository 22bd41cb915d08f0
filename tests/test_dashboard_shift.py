"""The dashboard's Shift panel in a real browser: the figures of `cellctl report shift` (the
API's report.shift) after a real batch; what the shift hands over (parts held, alarms open at
its end) and the controller's time and events, in the text report's words."""

from __future__ import annotations

import re
from datetime import datetime
from pathlib import Path

from playwright.async_api import Browser, Locator

from cellctl.service.rpc import Caller
from cellctl.testing.rig import CellRig
from tests.conftest import IN_BROWSER, SEEN_MS
from tests.test_cell_crash import spawn_controller

# dash: the fixture; _dash_page: the same page for a cell a test starts itself.
from tests.test_dashboard import Dash, _dash_page, dash, dashboard_served, live  # noqa: F401
from tests.test_dashboard_phone import PHONE, STICKING_OUT

# On the session's event loop, where the browser lives (tests/conftest.py).
pytestmark = IN_BROWSER


async def test_the_shift_panel_shows_the_reports_figures(dash: Dash) -> None:  # noqa: F811
    rig = dash.rig
    await live(dash)
    rig.post("wax-robot-base", 1, "S1")
    await rig.wait_for(rig.all_done, "order S1 done", timeout=60)
    found = await dash.api("report.shift")
    assert found["parts_good"] == 1
    page = dash.page
    parts = page.locator("#shift-parts", has_text="parts good 1, held 0, scrapped 0")
    await parts.wait_for(timeout=15_000)
    for m in found["machines"]:
        row = page.locator(f'#shift-machines tr[data-machine="{m["machine"]}"]')
        cells = await row.locator("td").all_inner_texts()
        assert cells[0] == m["machine"]
        assert cells[-1] == f"{m['steps_good']} / {m['steps_ended']}"
        assert cells[3] == f"{100 * m['quality']:.1f} %"
    await dash.shot("shift", "#shift")


async def test_a_ratio_not_known_yet_reads_as_a_dash(dash: Dash) -> None:  # noqa: F811
    """Before a step ended, quality (and OEE with it) is not known: the panel shows the
    report's dash, as `cellctl report shift` does, not 0 %."""
    await live(dash)
    found = await dash.api("report.shift")
    unknown = [m for m in found["machines"] if m["quality"] is None]
    assert unknown, found  # nothing ordered yet: no step ended
    for m in unknown:
        row = dash.page.locator(f'#shift-machines tr[data-machine="{m["machine"]}"]')
        await row.wait_for(timeout=15_000)
        cells = await row.locator("td").all_inner_texts()
        assert cells[3] == "\u2014", cells
        assert cells[4] == "\u2014", cells


def _day_time(t: float) -> str:
    """``t`` as the panel's lists show it, with its day (the text report's MM-DD HH:MM:SS)."""
    return datetime.fromtimestamp(t).strftime("%m-%d %H:%M:%S")


def _words(item: str) -> str:
    """An event of the panel's list without its time (MM-DD HH:MM:SS)."""
    return item.split(" ", 2)[2]


async def _cells(row: Locator) -> list[str]:
    await row.wait_for(timeout=SEEN_MS)
    return await row.locator("td").all_inner_texts()


async def test_the_panel_hands_over_the_shift_and_says_who_paused(dash: Dash) -> None:  # noqa: F811
    """What an operator taking over reads first (the parts held and the alarms open at the
    window's end), and the controller's time and events, in `cellctl report shift`'s words:
    who paused and resumed the cell, an emergency stop's reason, an alarm acknowledged by
    whom, one not."""
    rig = dash.rig
    api = dash.server.dispatcher
    olga, eve = Caller("token:olga", "operator"), Caller("token:eve", "engineer")
    # The window begins at the journal's first step: a batch first, the rest after it.
    rig.post("wax-robot-base", 1, "S1")
    await rig.wait_for(rig.all_done, "order S1 done", timeout=60)
    await api.call("cell.pause", {}, caller=olga)
    rig.post("wax-robot-base", 1, "H1")
    (part,) = await rig.wait_for(lambda: rig.journal.parts(order_id="H1"), "H1's part")
    held = rig.journal.hold_part(part.id, "inspect the blank")
    await api.call("cell.resume", {}, caller=eve)
    await api.call("cell.estop", {"reason": "smoke at cnc1"}, caller=eve)
    (stop,) = rig.alarms("cell", "estop")
    await api.call("alarms.ack", {"id": stop.id}, caller=olga)
    rig.cell.plc.set_fault("estop", None)  # the button pressed as well: left unacknowledged
    (button,) = await rig.wait_for(lambda: rig.alarms("plc", "estop"), "the button's alarm")
    # Opened now, the page reads the report at once: all of the above is in it.
    await live(dash)
    page = dash.page

    cells = await _cells(page.locator(f'#shift-held tr[data-part="{part.id}"]'))
    assert cells == [part.id, "wax-robot-base", held.location, _day_time(held.updated),
                     "inspect the blank"]  # fmt: skip
    cells = await _cells(page.locator(f'#shift-open-alarms tr[data-alarm="{stop.id}"]'))
    assert cells[3:] == ["cell", "estop", "emergency stop: smoke at cnc1",
                         "still active, acknowledged by token:olga"]  # fmt: skip
    row = page.locator(f'#shift-open-alarms tr.unacked[data-alarm="{button.id}"]')
    cells = await _cells(row)
    assert cells[3:5] == ["plc", "estop"] and cells[-1] == "still active, not acknowledged"
    handover = await page.locator("#shift-handover").inner_text()
    opened = [(a["machine"], a["code"]) for a in await dash.api("alarms.list")]
    assert handover == "at the window's end: 1 part held, 2 alarms open (1 not acknowledged)", (
        opened  # an alarm no page test is about (a loaded box), named in the failure
    )

    # The controller started before the window (its first step): nothing of it not known.
    split = await page.locator("#shift-controller").inner_text()
    assert re.fullmatch(r"controller: running \S+( s)?, paused \S+( s)?, stopped 0\.0 s", split), (
        split
    )
    events = await page.locator("#shift-events li").all_inner_texts()
    assert [_words(e) for e in events] == [
        "paused by token:olga (operator)",
        "resumed by token:eve (engineer)",
        "paused by token:eve (engineer): emergency stop: smoke at cnc1",
    ], events
    await dash.shot("shift-handover", "#shift")

    # On a phone the two columns go one under the other; nothing sticks out of the screen.
    await page.set_viewport_size(PHONE)
    assert await page.evaluate(STICKING_OUT) == []
    await dash.shot("shift-handover-phone", "#shift")


async def test_nothing_to_hand_over_is_said_so(dash: Dash) -> None:  # noqa: F811
    await live(dash)
    page = dash.page
    line = page.locator("#shift-handover")
    await line.filter(has_text="at the window's end").wait_for(timeout=SEEN_MS)
    assert await line.inner_text() == "at the window's end: no part held, no alarm open"
    # No empty table under it: the line said it all.
    assert await page.locator("#shift-held-box").is_hidden()
    assert await page.locator("#shift-open-alarms-box").is_hidden()
    assert (await page.locator("#shift-controller").inner_text()).startswith("controller: running ")


async def test_a_controller_that_ended_without_stopping_is_said_so(
    tmp_path: Path, browser: Browser
) -> None:
    """A controller killed (kill -9: no "stopped" in the journal) after a batch, then started
    again: the panel says the first ended without stopping, as the text report does, and
    the time until the next start is not known."""
    # The dash fixture's options (tests/test_dashboard.py): deadlines for a loaded box.
    async with CellRig(
        tmp_path / "cell", cell_options={"read_limit": 5.0}, plc_options={"timeout": 5.0}
    ) as rig:
        killed = await spawn_controller(rig.directory, tmp_path / "killed.log")
        try:
            rig.post("wax-robot-base", 1, "K1")
            await rig.wait_for(rig.all_done, "order K1 done", timeout=60)
        finally:
            killed.kill()
            await killed.wait()
        await rig.start_controller()
        async with (
            dashboard_served(rig) as (server, base),
            _dash_page(rig, server, base, browser, tmp_path) as dash,
        ):
            await live(dash)
            unheard = dash.page.locator('#shift-events li[data-event="ended unheard"]')
            await unheard.wait_for(timeout=SEEN_MS)
            said = await unheard.inner_text()
            assert said.endswith("ended without stopping (a crash, a kill?): last heard of then")
            events = await dash.page.locator("#shift-events li").all_inner_texts()
            assert _words(events[-1]) == "started", events
            split = await dash.page.locator("#shift-controller").inner_text()
            assert re.fullmatch(
                r"controller: running \S+( s)?, paused 0\.0 s, stopped 0\.0 s, "
                r"not known \S+( s)?",
                split,
            ), split
