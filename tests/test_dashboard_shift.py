"""The dashboard's Shift panel in a real browser: the figures of `cellctl report shift` (the
API's report.shift) after a real batch."""

from __future__ import annotations

from tests.conftest import IN_BROWSER
from tests.test_dashboard import Dash, dash, live  # noqa: F401 (the fixture)

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
