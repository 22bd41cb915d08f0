"""The dashboard in a real browser (Debian's Chromium through Playwright) against the emulated
cell and the real controller: the token, the live floor, orders, alarms, held parts, and
requests from another origin. A screenshot of each view lands in the test's tmp dir
(``CELLCTL_SCREENSHOT=docs/dashboard.png`` also writes the floor with a batch running there)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import time
import urllib.error
import urllib.request
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from playwright.async_api import Browser, Page
from playwright.async_api import Error as PlaywrightError
from playwright.async_api import TimeoutError as PlaywrightTimeout
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from cellctl.service.access import AttachedCell
from cellctl.service.server import ApiServer
from cellctl.testing.rig import CellRig, cli
from cellctl.ui.dashboard import dashboard_routes
from tests.conftest import IN_BROWSER, SEEN_MS, free_port


@dataclass
class Dash:
    rig: CellRig
    server: ApiServer
    base: str
    page: Page
    shots: Path
    server_routes: Any = dashboard_routes

    @property
    def token(self) -> str:
        return self.server.token

    async def open(self, fragment: str | None = None) -> None:
        tail = f"#token={self.token}" if fragment is None else fragment
        await self.page.goto("about:blank")  # a new fragment alone would not load the page
        await self.page.goto(f"{self.base}/{tail}")

    async def shot(self, name: str, selector: str | None = None) -> Path:
        path = self.shots / f"{name}.png"
        if selector is None:
            await self.page.screenshot(path=str(path))
        else:
            await self.page.locator(selector).screenshot(path=str(path))
        return path

    async def confirm(self) -> None:
        await self.page.locator("#confirm-yes").click()

    async def api(self, method: str, params: dict[str, Any] | None = None) -> Any:
        return await self.server.dispatcher.call(method, params or {})


@contextlib.asynccontextmanager
async def dashboard_served(rig: CellRig) -> AsyncIterator[tuple[ApiServer, str]]:
    """``rig``'s running controller's API with the dashboard, on a free loopback port: the
    server and its base URL (closed after)."""
    assert rig.controller is not None
    port = free_port()
    server = ApiServer(
        AttachedCell(rig.controller),
        rig.directory,
        listen=f"127.0.0.1:{port}",
        extra_routes=dashboard_routes,
    )
    await server.start()
    try:
        yield server, f"http://127.0.0.1:{port}"
    finally:
        await server.close()


async def http(
    url: str,
    *,
    token: str | None = None,
    body: Any = None,
    headers: dict[str, str] | None = None,
    timeout: float = 5.0,
) -> tuple[int, Any]:
    """One request (GET, or POST with a JSON ``body``) from another thread (the server runs in
    this one): status and decoded JSON, within ``timeout`` s."""
    return await asyncio.to_thread(_http, url, token, body, headers, timeout)


def _http(
    url: str, token: str | None, body: Any, headers: dict[str, str] | None, timeout: float
) -> tuple[int, Any]:
    sent = dict(headers or {})
    if token is not None:
        sent["Authorization"] = f"Bearer {token}"
    data = None
    if body is not None:
        data = json.dumps(body).encode()
        sent.setdefault("Content-Type", "application/json")
    request = urllib.request.Request(url, data=data, headers=sent)
    try:
        with urllib.request.urlopen(request, timeout=timeout) as answer:
            return answer.status, json.loads(answer.read() or b"null")
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"null")


pytestmark = IN_BROWSER


@pytest_asyncio.fixture(loop_scope="session")
async def dash(
    tmp_path: Path, browser: Browser, request: pytest.FixtureRequest
) -> AsyncIterator[Dash]:
    # A test may ask for a slower cell (parametrize "dash" indirectly with its time scale).
    scale = getattr(request, "param", None)
    # The cell shares this process with the page's driver, and the box with Chromium: on a
    # loaded box a PLC answer, or a look at an idle machine, can take over its 1 s test
    # deadline, which raises a link alarm for a reason no page test is about
    # (tests/test_cell_faults.py is where a silent machine is, on virtual time).
    loaded_s = 5.0
    async with CellRig(
        tmp_path / "cell",
        cell_options={"read_limit": loaded_s},
        plc_options={"timeout": loaded_s},
        **({"time_scale": scale} if scale else {}),
    ) as rig:
        await rig.start_controller()
        async with contextlib.AsyncExitStack() as stack:
            server, base = await stack.enter_async_context(dashboard_served(rig))
            dash = await stack.enter_async_context(_dash_page(rig, server, base, browser, tmp_path))
            yield dash


@contextlib.asynccontextmanager
async def _dash_page(
    rig: CellRig, server: ApiServer, base: str, browser: Browser, tmp_path: Path
) -> AsyncIterator[Dash]:
    """A page in Chromium for the dashboard ``server`` serves at ``base``; after the test, no
    error the page reported, and a server a test started in ``server``'s place closed."""
    context = await browser.new_context(viewport={"width": 1400, "height": 1000})
    page = await context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on(
        "console",
        lambda m: errors.append(m.text) if "Content Security Policy" in m.text else None,
    )
    shots = tmp_path / "screenshots"
    shots.mkdir()
    dash = Dash(rig, server, base, page, shots)
    try:
        yield dash
        assert not errors, f"the page reported errors: {errors}"
    finally:
        await context.close()
        if dash.server is not server:  # a test's own, started in its place
            await dash.server.close()


def _shell(base: str) -> tuple[str, str]:
    with urllib.request.urlopen(base + "/", timeout=5) as answer:
        return answer.read().decode(), answer.headers["Content-Security-Policy"]


async def live(dash: Dash) -> None:
    """Open the dashboard and wait until it shows the live cell."""
    await dash.open()
    await dash.page.locator("#connection.good").wait_for(timeout=SEEN_MS)
    await dash.page.locator("#floor-plan svg .machine.mill").first.wait_for(timeout=SEEN_MS)


async def test_the_token_is_needed_for_the_page_and_the_api(dash: Dash) -> None:
    for fragment in ("", "#token=wrong-token"):
        await dash.open(fragment)
        await dash.page.locator("#refused").wait_for(state="visible", timeout=SEEN_MS)
        assert await dash.page.locator("#content").is_hidden()
        assert await dash.page.locator("#content > *").count() == 0  # no cell data at all
        assert "refused" in (await dash.page.locator("#connection").inner_text()).lower()
    await dash.shot("refused")
    for token in (None, "wrong-token"):
        for path in ("/api/status", "/api/parts", "/access/oneshot_token"):
            status, body = await http(dash.base + path, token=token)
            assert status == 401 and "cell" not in body, path
        status, body = await http(
            dash.base + "/dashboard/call", token=token, body={"method": "cell.status"}
        )
        assert status == 401 and "result" not in body
    # The shell itself carries no cell data, and the token never appears in the address bar.
    shell, csp = await asyncio.to_thread(_shell, dash.base)
    assert "script-src 'self'" in csp and "wax-robot-base" not in shell
    await live(dash)
    assert "token" not in dash.page.url
    assert await dash.page.locator("#refused").is_hidden()
    assert await dash.page.locator("#cell-name").inner_text() != "cellctl"


def cutting(rig: Any) -> bool:
    """Whether a mill is in a cut now, with a block to show."""
    machines = rig.controller.machines if rig.controller else {}
    return any((v.progress or {}).get("block") for v in machines.values() if v.name != "robot")


async def shown_while(marker: Any, still: Callable[[], bool], what: str) -> bool:
    """Whether the page shows ``marker`` while ``still()`` holds; False when it stopped
    holding first. What still holds and is not shown within SEEN_MS fails the test."""
    deadline = time.monotonic() + SEEN_MS / 1000
    while True:
        with contextlib.suppress(PlaywrightError):
            await marker.wait_for(state="attached", timeout=500)
            return True
        if not still():
            return False
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}, not on the page")


# Cuts of a few seconds: at the default scale a part may be at a mill for less time than a
# loaded box's page takes to draw it, and a test that saw too few moves says nothing.
@pytest.mark.parametrize("dash", [200.0], indirect=True)
async def test_the_floor_follows_the_batch(dash: Dash) -> None:
    rig = dash.rig
    await live(dash)
    rig.post("wax-robot-base", 2, "F1")
    rig.post("wax-toy-mill-table", 1, "F2")
    page = dash.page
    moves_seen = 0
    last: dict[str, str] = {}
    deadline = time.monotonic() + 40
    shot_taken = False
    while (moves_seen < 3 or not shot_taken) and time.monotonic() < deadline:
        rig.check_running()
        for part in rig.journal.parts(["waiting", "active", "held"]):
            if last.get(part.id, "conveyor") != part.location:
                marker = page.locator(
                    f'[data-part-id="{part.id}"][data-location="{part.location}"]'
                )
                there = lambda p=part: rig.journal.get_part(p.id).location == p.location  # noqa: E731
                if not await shown_while(marker, there, f"part {part.id} at {part.location}"):
                    continue  # it moved on again before the page was looked at
                moves_seen += 1
            last[part.id] = part.location
        if not shot_taken and cutting(rig):
            # A cutting mill's card shows it busy, with its step and part as fields give them.
            busy = page.locator(".card.condition-busy", has=page.locator(".preview svg"))
            current = page.locator(".preview svg .block-start.current").first
            if not (
                await shown_while(current, lambda: cutting(rig), "a mill's current block")
                and await shown_while(busy.first, lambda: cutting(rig), "a busy mill's card")
            ):
                continue  # the cut ended before the page was looked at: wait for the next
            assert (await busy.first.locator(".step").inner_text()).startswith("machine ")
            await asyncio.sleep(0.6)  # the parts' moves on the floor are animated (0.5 s)
            await dash.shot("machines", "#machines")
            target = os.environ.get("CELLCTL_SCREENSHOT")
            await dash.shot("floor")
            if target:
                await page.screenshot(path=target)
            shot_taken = True
        await asyncio.sleep(0.02)
    assert moves_seen >= 3, f"saw {moves_seen} moves on the page\n{rig.describe()}"
    assert shot_taken, "no mill showed its cut's progress"
    await dash.shot("floor-panel", "#floor")
    # The Gantt chart draws the journal's steps; exported as SVG it is a file of its own.
    await page.locator("#gantt-chart svg rect.step").first.wait_for(timeout=SEEN_MS)
    await dash.shot("gantt", "#gantt")
    async with page.expect_download() as download:
        await page.locator("#gantt-svg").click()
    saved = dash.shots / "gantt.svg"
    await (await download.value).save_as(saved)
    assert saved.read_text().startswith("<svg") and "rect" in saved.read_text()
    async with page.expect_download() as download:
        await page.locator("#gantt-png").click()
    png = dash.shots / "gantt.png"
    await (await download.value).save_as(png)
    assert png.read_bytes().startswith(b"\x89PNG\r\n\x1a\n") and png.stat().st_size > 1000
    # Traffic: the robot's last bytes, both ways.
    await page.select_option("#traffic-machine", "robot")
    await page.locator("#traffic-table tr.received").first.wait_for(timeout=SEEN_MS)
    await page.locator("#traffic-table tr.sent").first.wait_for(timeout=SEEN_MS)
    await dash.shot("traffic", "#traffic")


async def test_an_order_from_the_form(dash: Dash) -> None:
    await dash.api("cell.pause")
    await live(dash)
    page = dash.page
    await page.select_option("#order-type", "wax-toy-mill-table")
    await page.fill("#order-qty", "2")
    await page.fill("#order-priority", "5")
    await page.click("#order-submit")
    message = page.locator("#order-message.ok")
    await message.wait_for(timeout=SEEN_MS)
    assert "posted" in await message.inner_text()
    row = page.locator("#order-table tbody tr", has_text="wax-toy-mill-table")
    await row.wait_for(timeout=SEEN_MS)
    orders = await dash.api("orders.list")
    assert [(o["part_type"], o["qty"], o["priority"]) for o in orders] == [
        ("wax-toy-mill-table", 2, 5)
    ]
    await page.fill("#order-qty", "0")
    await page.click("#order-submit")
    refused = page.locator("#order-message.error")
    await refused.wait_for(timeout=SEEN_MS)
    text = await refused.inner_text()
    assert "qty" in text and "greater than or equal to 1" in text, text
    assert len(await dash.api("orders.list")) == 1
    await dash.shot("orders", "#orders")
    # Cancel it (it has not started): confirmed first.
    await row.locator("button", has_text="Cancel").click()
    assert "Cancel order" in await page.locator("#confirm-text").inner_text()
    await dash.confirm()
    await page.locator("#order-table tbody tr.order-cancelled").wait_for(timeout=SEEN_MS)
    assert (await dash.api("orders.list"))[0]["state"] == "cancelled"


async def test_an_alarm_is_acknowledged_then_cleared_from_the_page(dash: Dash) -> None:
    await live(dash)
    rig = dash.rig
    page = dash.page
    rig.cell.plc.set_fault("estop", None)
    row = page.locator("#alarm-table tbody tr[data-alarm]", has_text="emergency stop")
    await row.wait_for(timeout=SEEN_MS)
    # Unacknowledged: the row is marked and the header's badge flashes until Ack.
    badge = page.locator("#alarm-badge.flashing")
    await badge.wait_for(timeout=SEEN_MS)
    # Its text, not its rendering: the flashing badge is hidden every other half second.
    assert "1 unacknowledged" in (await badge.text_content() or "")
    assert "unacked" in (await row.get_attribute("class") or "")
    assert "high" in await row.inner_text()
    await dash.shot("alarms", "#attention")
    rig.cell.plc.clear_fault("estop")
    # The monitor sees the PLC well again: returned to normal, still unacknowledged.
    await row.locator(".alarm-state", has_text="returned to normal").wait_for(timeout=SEEN_MS)
    assert await page.locator("#alarm-badge.flashing").count() == 1
    alarm_id = int(await row.get_attribute("data-alarm") or 0)
    # A wrong token cannot acknowledge it.
    call = {"method": "alarms.ack", "params": {"id": alarm_id}}
    status, _ = await http(dash.base + "/dashboard/call", token="wrong", body=call)
    assert status == 401
    [still] = [a for a in await dash.api("alarms.list") if a["id"] == alarm_id]
    assert still["acked"] is None
    await row.locator("button", has_text="Ack").click()  # no confirmation: it only marks seen
    try:
        await page.locator("#alarm-badge.hidden").wait_for(state="attached", timeout=SEEN_MS)
    except PlaywrightTimeout:  # which alarm kept the badge up, in the failure
        badge_text = await page.locator("#alarm-badge").text_content()
        alarms = await dash.api("alarms.list")
        raise AssertionError(f"badge {badge_text!r}; alarms: {alarms}") from None
    await row.locator(".alarm-state", has_text="acknowledged, returned").wait_for(timeout=SEEN_MS)
    [acked] = [a for a in await dash.api("alarms.list") if a["id"] == alarm_id]
    assert acked["acked"] is not None and acked["state"] == "active"  # acked is not cleared
    await row.locator("button", has_text="Clear").click()
    await dash.confirm()
    await dash.page.locator(f'#alarm-table tr[data-alarm="{alarm_id}"]').wait_for(
        state="detached", timeout=SEEN_MS
    )
    status, alarms = await http(dash.base + "/api/alarms", token=dash.token)
    assert status == 200 and alarm_id not in [a["id"] for a in alarms]
    # The pushed status may remove the row before the call's own answer is shown.
    await dash.page.locator("#alarm-message", has_text="cleared").wait_for(timeout=SEEN_MS)


async def test_a_card_and_the_floor_show_a_machine_out_of_service(dash: Dash) -> None:
    await live(dash)
    page = dash.page
    card = page.locator('#machine-cards .card[data-machine="cnc2"]')
    await card.and_(page.locator('[data-condition="idle"]')).wait_for(timeout=SEEN_MS)
    await dash.api("machines.out_of_service", {"machine": "cnc2", "reason": "new cutter"})
    out = page.locator('#machine-cards .card.condition-out-of-service[data-machine="cnc2"]')
    await out.wait_for(timeout=SEEN_MS)
    assert await out.locator(".badge.state").inner_text() == "out of service"
    assert "new cutter" in await out.locator(".machine-state").inner_text()
    floor = page.locator('#floor-plan .machine[data-machine="cnc2"]')
    assert await floor.get_attribute("data-condition") == "out-of-service"
    assert "state-out-of-service" in (await floor.get_attribute("class") or "")
    # The other mill is read by its own condition: untouched.
    assert (
        await page.locator('.card[data-machine="cnc1"]').get_attribute("data-condition") == "idle"
    )
    await dash.shot("out-of-service", "#machines")
    await dash.api("machines.return_to_service", {"machine": "cnc2"})
    await card.and_(page.locator('[data-condition="idle"]')).wait_for(timeout=SEEN_MS)


async def test_a_held_part_is_released_from_the_page(dash: Dash) -> None:
    await dash.api("cell.pause")
    rig = dash.rig
    rig.post("wax-robot-base", 1, "H1")
    await live(dash)
    parts = await rig.wait_for(lambda: rig.journal.parts(order_id="H1"), "H1's part")
    rig.journal.hold_part(parts[0].id, "inspect the blank")
    rig.controller.poke()  # type: ignore[union-attr]
    row = dash.page.locator(f'#held-table tr[data-part="{parts[0].id}"]')
    await row.wait_for(timeout=SEEN_MS)
    assert "inspect the blank" in await row.inner_text()
    await dash.shot("held", "#attention")
    await row.locator("button", has_text="Release").first.click()
    await dash.confirm()
    await row.wait_for(state="detached", timeout=SEEN_MS)
    assert rig.journal.get_part(parts[0].id).status == "waiting"
    # The row goes with the pushed status; the call's own answer may come a moment later.
    message = dash.page.locator("#part-message", has_text=re.compile("released", re.IGNORECASE))
    await message.wait_for(timeout=SEEN_MS)


async def test_redo_refused_and_scrap_on_a_tablet(dash: Dash) -> None:
    await dash.api("cell.pause")
    rig = dash.rig
    rig.post("wax-robot-base", 2, "H2")
    await dash.page.set_viewport_size({"width": 820, "height": 1180})  # a tablet, upright
    await live(dash)
    parts = await rig.wait_for(lambda: rig.journal.parts(order_id="H2"), "H2's parts")
    assert len(parts) == 2
    rig.journal.move_part(parts[1].id, "cnc1")  # where the arm left it
    for part in parts:
        rig.journal.hold_part(part.id, "chipped edge")
    rig.controller.poke()  # type: ignore[union-attr]
    page = dash.page
    redo, scrap = (page.locator(f'#held-table tr[data-part="{p.id}"]') for p in parts)
    await redo.wait_for(timeout=SEEN_MS)
    await scrap.wait_for(timeout=SEEN_MS)
    # Nothing is wider than the screen: every panel reflows.
    width = await page.evaluate("document.documentElement.scrollWidth - window.innerWidth")
    assert width <= 0, f"the page is {width} px wider than a tablet"
    await dash.shot("tablet")
    # Held by hand, it has no step to redo: refused in the journal's words, nothing changed.
    await redo.locator("button", has_text="Release & redo").click()
    await dash.confirm()
    refusal = page.locator("#part-message.error")
    await refusal.wait_for(timeout=SEEN_MS)
    assert "has no step to redo" in await refusal.inner_text()
    assert rig.journal.get_part(parts[0].id).status == "held"
    await scrap.locator("button", has_text="Scrap").click()
    asked = await page.locator("#confirm-text").inner_text()
    # The confirmation names the machine: it is the operator's word that the part is out.
    assert f"Scrap part {parts[1].id}? It may be in cnc1: take it out first" in asked
    assert "cannot be undone" in asked
    await dash.confirm()
    await scrap.wait_for(state="detached", timeout=SEEN_MS)
    assert rig.journal.get_part(parts[1].id).status == "scrapped"
    [scrapped] = rig.reports("part-scrapped")
    assert scrapped.data["taken_out_of"] == ["cnc1"]


async def test_another_origin_cannot_drive_the_cell(dash: Dash) -> None:
    evil = {"Origin": "http://evil.example"}
    call = {"method": "orders.submit", "params": {"part_type": "wax-robot-base"}}
    status, body = await http(
        dash.base + "/dashboard/call", token=dash.token, body=call, headers=evil
    )
    assert status == 403 and "another origin" in body["error"]["message"]
    assert body["error"]["code"] == -32007  # AccessDenied, as the API codes it
    status, _ = await http(dash.base + "/dashboard/call", body=call)
    assert status == 401
    # What is wrong with the request itself has JSON-RPC's own codes.
    status, body = await http(
        dash.base + "/dashboard/call", token=dash.token, body={"method": "robot.go"}
    )
    assert (status, body["error"]["code"]) == (400, -32601), body

    def broken() -> tuple[int, Any]:
        request = urllib.request.Request(
            dash.base + "/dashboard/call",
            data=b"{not json",
            headers={"Authorization": f"Bearer {dash.token}", "Content-Type": "application/json"},
        )
        try:
            with urllib.request.urlopen(request, timeout=5) as answer:
                return answer.status, json.loads(answer.read())
        except urllib.error.HTTPError as e:
            return e.code, json.loads(e.read())

    status, body = await asyncio.to_thread(broken)
    assert (status, body["error"]["code"]) == (400, -32700), body
    assert await dash.api("orders.list") == []
    # A WebSocket from another site is refused even with a good one-shot token.
    status, oneshot = await http(dash.base + "/access/oneshot_token", token=dash.token)
    assert status == 200
    url = f"ws://127.0.0.1:{dash.base.rsplit(':', 1)[1]}/websocket?token={oneshot['token']}"
    with pytest.raises(InvalidStatus) as refused:
        async with connect(url, additional_headers=evil):
            pass
    assert refused.value.response.status_code == 403
    # ... and its own page's origin gets through.
    status, body = await http(
        dash.base + "/dashboard/call",
        token=dash.token,
        body={"method": "cell.layout"},
        headers={"Origin": dash.base},
    )
    assert status == 200 and body["result"]["mills"] == ["cnc1", "cnc2"]


async def test_a_preview_is_drawn_only_for_a_program_of_the_routes(dash: Dash) -> None:
    drawn = await dash.api(
        "programs.preview", {"machine": "cnc1", "program": "robot_base_rough_cnc1"}
    )
    assert drawn["svg"].startswith("<svg") and 'class="block-start"' in drawn["svg"]
    again = await dash.api(
        "programs.preview", {"machine": "cnc1", "program": "programs/robot_base_rough_cnc1.dyn"}
    )
    assert again == drawn
    for machine, program in [
        ("cnc1", "../../etc/passwd"),
        ("cnc1", "programs/cnc1_setup.dyn"),
        ("cnc2", "robot_base_rough_cnc1"),  # cnc1's, not cnc2's
        ("robot", "robot_base_rough_cnc1"),
    ]:
        status, body = await http(
            dash.base + "/dashboard/call",
            token=dash.token,
            body={"method": "programs.preview", "params": {"machine": machine, "program": program}},
        )
        assert status == 400 and "svg" not in json.dumps(body), (machine, program)
        assert body["error"]["data"]["type"] == "UsageError"


async def test_the_page_reconnects_after_the_controller_restarts(dash: Dash) -> None:
    await live(dash)
    port = int(dash.base.rsplit(":", 1)[1])
    await dash.server.close()
    connection = dash.page.locator("#connection")
    await dash.page.locator("#connection.bad").wait_for(timeout=SEEN_MS)
    assert "reconnecting" in await connection.inner_text()
    assert dash.rig.controller is not None
    dash.server = ApiServer(
        AttachedCell(dash.rig.controller),
        dash.rig.directory,
        listen=f"127.0.0.1:{port}",
        extra_routes=dash.server_routes,
    )
    await dash.server.start()
    await dash.page.locator("#connection.good").wait_for(timeout=SEEN_MS)
    assert "reconnected" in await connection.inner_text()
    assert await dash.page.locator("#notice").is_hidden()


async def test_cellctl_dashboard_refuses_clearly_and_prints_the_url(
    dash: Dash, monkeypatch: pytest.MonkeyPatch
) -> None:
    directory = dash.rig.directory
    toml = directory / "cell.toml"
    text = toml.read_text()
    result = await cli(directory, "dashboard", "--print")
    assert result.exit_code == 2 and "names no [api] listen" in result.output
    port = int(dash.base.rsplit(":", 1)[1])
    toml.write_text(text + f'\n[api]\nlisten = "127.0.0.1:{port}"\n')
    result = await cli(directory, "dashboard", "--print")
    assert result.exit_code == 0, result.output
    assert result.output.strip() == f"{dash.base}/#token={dash.token}"
    # Without the cell's own token file, $CELLCTL_TOKEN serves, as for every client.
    (directory / "api-token").rename(directory / "api-token.away")
    monkeypatch.setenv("CELLCTL_TOKEN", dash.token)
    result = await cli(directory, "dashboard", "--print")
    assert result.exit_code == 0, result.output
    monkeypatch.delenv("CELLCTL_TOKEN")
    result = await cli(directory, "dashboard", "--print")
    assert result.exit_code == 2 and "no API token in" in result.output
    assert "no $CELLCTL_TOKEN" in result.output
    (directory / "api-token.away").rename(directory / "api-token")
    toml.write_text(text + f'\n[api]\nlisten = "127.0.0.1:{free_port()}"\n')
    result = await cli(directory, "dashboard", "--print")
    assert result.exit_code == 2 and "no controller answers" in result.output
    assert dash.token not in result.output


async def test_after_a_reload_each_event_shows_once(dash: Dash) -> None:
    await live(dash)
    page = dash.page
    for i in range(2):  # a reload reads the status, then is pushed updates on top of it
        # Events to hold: a machine out of service and back (each a line of the Events panel).
        await dash.api("machines.out_of_service", {"machine": "cnc2", "reason": f"check {i}"})
        await dash.api("machines.return_to_service", {"machine": "cnc2"})
        await page.locator("#event-list li", has_text=f"check {i}").wait_for(timeout=SEEN_MS)
        await page.reload()
        await page.locator("#connection.good").wait_for(timeout=SEEN_MS)
        await page.locator("#event-list li", has_text=f"check {i}").wait_for(timeout=SEEN_MS)
        # A push after the read (one more event) must not bring the earlier ones again.
        await dash.api("machines.out_of_service", {"machine": "cnc1", "reason": f"push {i}"})
        await page.locator("#event-list li", has_text=f"push {i}").wait_for(timeout=SEEN_MS)
        # The cell's events before and after the page is read, the same (an alarm a loaded
        # box raises meanwhile is on the page and in the log, or in neither).
        for _ in range(50):
            before = [e["text"] for e in (await dash.api("cell.status", {}))["events"]]
            shown = await page.locator("#event-list li").evaluate_all(
                "items => items.map((li) => li.lastChild.textContent)"
            )
            after = [e["text"] for e in (await dash.api("cell.status", {}))["events"]]
            if before == after:
                break
            await asyncio.sleep(0.1)
        held = after[-15:]
        # The page shows the newest 15, newest first: each as often as the cell logged it.
        for text in set(shown):
            assert shown.count(text) == held.count(text), (
                f"{text!r} shown {shown.count(text)} times, logged {held.count(text)}: {shown}"
            )
        await dash.api("machines.return_to_service", {"machine": "cnc1"})
