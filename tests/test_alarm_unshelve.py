"""Unshelving an alarm (ISA-18.2): a shelved alarm is shown as it is again at once, before its
shelve runs out, from every surface: the journal, the command line through a running cell's
API (an operator may, a viewer is refused with the role it lacks; both on the audit trail),
the console's ALARMS dialog and the dashboard's Unshelve control. An alarm that is not shelved
now (never, or its time ran out) or is cleared is refused in words.

The cell is the emulated one, its controller and API in this process; the alarm is the PLC's
emergency stop, raised by the emulated PLC's fault switch."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from textual.pilot import Pilot

from cellctl.cell.journal import Alarm, Journal
from cellctl.errors import AccessDenied, UsageError
from cellctl.service.audit import AuditLog
from cellctl.service.client import CellClient, RemoteCell
from cellctl.service.token import TOKEN_ENV, add_token
from cellctl.testing.rig import CellRig
from cellctl.ui.cli import main as cli_main
from cellctl.ui.console.app import ConsoleApp
from tests import test_api, test_console, test_dashboard
from tests.conftest import IN_BROWSER, SEEN_MS
from tests.test_alarm_states import Clock
from tests.test_api import Api
from tests.test_console import SIZE, wait_text
from tests.test_dashboard import Dash, live

# The running cells of the other tests, as they start them: the API's (controller and API in
# this process), the console's (deadlines for a loaded box) and the dashboard's.
api = test_api.api
rig = test_console.rig
attached = test_console.attached
dash = test_dashboard.dash


# -- the journal ------------------------------------------------------------------------------


def test_unshelving_shows_the_alarm_again_at_once(tmp_path: Path) -> None:
    clock = Clock()
    path = tmp_path / "j.sqlite3"
    with Journal(path, clock=clock) as journal:
        a, _ = journal.raise_alarm("cnc1", "link", "mill not answering")
        shelved = journal.shelve_alarm(a.id, 3600, by="ann")
        assert shelved.shelved(clock.at) and not shelved.unacked(clock.at)
        clock.at += 60
        back = journal.unshelve_alarm(a.id, by="bob")
        assert (back.shelved_until, back.shelved_by) == (None, "")
        assert back.unacked(clock.at)  # unacknowledged: shown so again, not an hour later
        assert journal.get_alarm(a.id) == back and journal.active_alarms() == [back]
        # Acknowledged before it was shelved: shown as it is, acknowledged.
        acked = journal.ack_alarm(a.id, by="ann")
        journal.shelve_alarm(a.id, 600, by="ann")
        again = journal.unshelve_alarm(a.id)
        assert again.acked == acked.acked and not again.shelved(clock.at)
    with Journal(path, clock=clock) as journal:  # on disk, not only in the views
        kept = journal.get_alarm(a.id)
        assert (kept.shelved_until, kept.shelved_by, kept.state) == (None, "", "active")


def test_only_an_alarm_shelved_now_is_unshelved(tmp_path: Path) -> None:
    clock = Clock()
    with Journal(tmp_path / "j.sqlite3", clock=clock) as journal:
        a, _ = journal.raise_alarm("plc", "conveyor", "no pallet within 30 s")
        with pytest.raises(UsageError, match=rf"^alarm {a.id} is not shelved$"):
            journal.unshelve_alarm(a.id)
        # A shelve that ran out counts as none: refused, and the alarm left as it was.
        journal.shelve_alarm(a.id, 60, by="ann")
        clock.at += 61
        with pytest.raises(UsageError, match=rf"alarm {a.id} is not shelved"):
            journal.unshelve_alarm(a.id)
        assert journal.get_alarm(a.id).shelved_by == "ann"
        # Unshelved once: a second unshelve is refused too.
        journal.shelve_alarm(a.id, 60)
        journal.unshelve_alarm(a.id)
        with pytest.raises(UsageError, match="is not shelved"):
            journal.unshelve_alarm(a.id)
        # Cleared while shelved: nothing to unshelve, and nothing changes.
        journal.shelve_alarm(a.id, 600)
        cleared = journal.clear_alarm(a.id)
        with pytest.raises(UsageError, match=rf"alarm {a.id} is cleared: nothing to unshelve"):
            journal.unshelve_alarm(a.id)
        assert journal.get_alarm(a.id) == cleared
        with pytest.raises(UsageError, match="no alarm 99"):
            journal.unshelve_alarm(99)


# -- the command line through a running cell's API ------------------------------------------


async def cli_as(cell: Path, token: str, *args: str) -> tuple[int, str]:
    """``cellctl --cell CELL ARGS`` acting with ``token`` ($CELLCTL_TOKEN), in a worker
    thread: through the running controller's API."""

    def invoke() -> tuple[int, str]:
        result = CliRunner().invoke(cli_main, ["--cell", str(cell), *args], env={TOKEN_ENV: token})
        return result.exit_code, result.output

    return await asyncio.to_thread(invoke)


async def estop_alarm(cell_rig: CellRig) -> Alarm:
    """The PLC's emergency stop alarm, its fault switched on and off (it stays open)."""
    cell_rig.cell.plc.set_fault("estop", None)
    [alarm] = await cell_rig.wait_for(lambda: cell_rig.alarms("plc", "estop"), "estop alarm")
    cell_rig.cell.plc.clear_fault("estop")
    return alarm


def said(out: str) -> str:
    """What a command printed, as one line (Rich wraps a long message at 80 columns)."""
    return " ".join(out.split())


async def shelved_until(cell: Path, token: str, alarm_id: int) -> float | None:
    """The alarm's ``shelved_until`` as ``cellctl alarm list --json`` gives it."""
    code, out = await cli_as(cell, token, "alarm", "list", "--json")
    assert code == 0, out
    [alarm] = [a for a in json.loads(out) if a["id"] == alarm_id]
    return alarm["shelved_until"]


async def test_an_operator_unshelves_from_the_cli_a_viewer_may_not(api: Api) -> None:
    cell_rig = api.rig
    cell = cell_rig.directory
    operator = add_token(cell, "otto", "operator")
    viewer = add_token(cell, "vera", "viewer")
    alarm = await estop_alarm(cell_rig)
    n = alarm.id

    code, out = await cli_as(cell, operator, "alarm", "shelve", str(n), "--for", "2h")
    assert code == 0 and f"alarm {n} shelved for 2h" in said(out), out
    assert await shelved_until(cell, viewer, n) is not None  # a viewer sees it shelved ...
    # ... and may not unshelve it: refused with the role it lacks, the alarm untouched.
    code, out = await cli_as(cell, viewer, "alarm", "unshelve", str(n))
    assert code != 0 and "vera is a viewer: alarms.unshelve needs the operator role" in said(out)
    assert cell_rig.journal.get_alarm(n).shelved_by == "token:otto"
    # The operator unshelves it: shown as it is again at once, unacknowledged.
    code, out = await cli_as(cell, operator, "alarm", "unshelve", str(n))
    assert code == 0 and f"alarm {n} unshelved (plc estop: {alarm.text})" in said(out), out
    assert await shelved_until(cell, viewer, n) is None
    now = cell_rig.journal.get_alarm(n)
    assert (now.shelved_by, now.state, now.acked) == ("", "active", None)
    # Not shelved any more: a second unshelve is refused in words; a shelve for no time says
    # what to do instead.
    code, out = await cli_as(cell, operator, "alarm", "unshelve", str(n))
    assert code == 2 and f"alarm {n} is not shelved" in said(out), out
    code, out = await cli_as(cell, operator, "alarm", "shelve", str(n), "--for", "0s")
    assert code == 2 and f"to show it again now: cellctl alarm unshelve {n}" in said(out), out
    # Cleared: nothing to unshelve.
    code, out = await cli_as(cell, operator, "alarm", "clear", str(n))
    assert code == 0, out
    code, out = await cli_as(cell, operator, "alarm", "unshelve", str(n))
    assert code == 2 and f"alarm {n} is cleared: nothing to unshelve" in said(out), out

    # The audit trail has each try: who, what, and its result.
    with AuditLog(cell) as log:
        tries = [
            (e.who, e.result)
            for e in log.entries(limit=10_000)
            if e.method == "alarms.unshelve" and f'"id":{n}' in e.params.replace(" ", "")
        ]
    assert tries == [
        ("token:vera", "vera is a viewer: alarms.unshelve needs the operator role"),
        ("token:otto", "ok"),
        ("token:otto", f"alarm {n} is not shelved"),
        ("token:otto", f"alarm {n} is cleared: nothing to unshelve"),
    ], tries


async def test_the_api_refuses_a_viewer_and_answers_an_operator(api: Api) -> None:
    cell_rig = api.rig
    socket_path = api.server.socket_path
    alarm = await estop_alarm(cell_rig)
    tokens = {r: add_token(cell_rig.directory, f"{r[:3]}1", r) for r in ("viewer", "operator")}
    viewer = await RemoteCell.connect(token=tokens["viewer"], socket_path=socket_path)
    operator = await RemoteCell.connect(token=tokens["operator"], socket_path=socket_path)
    try:
        info: dict[str, Any] = await viewer.call("server.info")
        assert info["roles"]["alarms.unshelve"] == info["roles"]["alarms.shelve"] == "operator"
        await operator.call("alarms.shelve", {"id": alarm.id, "seconds": 600})
        with pytest.raises(AccessDenied, match=r"alarms\.unshelve needs the operator role"):
            await viewer.call("alarms.unshelve", {"id": alarm.id})
        done = await operator.call("alarms.unshelve", {"id": alarm.id})
        assert done["message"] == f"alarm {alarm.id} unshelved (plc estop: {alarm.text})"
        assert done["alarm"]["shelved_until"] is None and done["alarm"]["shelved_by"] == ""
        [listed] = [a for a in await viewer.call("alarms.list") if a["id"] == alarm.id]
        assert listed["shelved_until"] is None
    finally:
        await viewer.close()
        await operator.close()


# -- the console --------------------------------------------------------------------------------


async def test_the_console_unshelves_from_the_alarms_dialog(
    rig: CellRig, attached: CellClient
) -> None:
    alarm = await estop_alarm(rig)
    n = alarm.id

    async def alarm_dialog(pilot: Pilot[Any]) -> str:
        """CELL → 4. ALARMS → Enter on the estop alarm: its choices, as shown."""
        await pilot.press("4")
        await wait_text(pilot, "ALARMS", f"{n} plc estop")
        ids = [a["id"] for a in await attached.call("alarms.list", {})]  # the rows' order
        await pilot.press(*["down"] * ids.index(n), "enter")
        return await wait_text(pilot, f"ALARM {n}", "1. ACKNOWLEDGE", "3. CLEAR")

    app = ConsoleApp(rig.directory, attached, traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "attached to cellctl run (pid")
        await pilot.press("c")
        await wait_text(pilot, "4. ALARMS")
        # Not shelved: no unshelve is offered. Shelved from here, for an hour.
        assert "UNSHELVE" not in await alarm_dialog(pilot)
        await pilot.press("2")
        await wait_text(pilot, f"alarm {n} shelved for 1h")
        assert rig.journal.get_alarm(n).shelved_by == "token:default"
        # Shelved: offered by its own number, after the source's three.
        shown = await alarm_dialog(pilot)
        assert "4. UNSHELVE (show it again now)" in shown, shown
        await pilot.press("4")
        await wait_text(pilot, f"alarm {n} unshelved (plc estop")
        unshelved = rig.journal.get_alarm(n)
        assert (unshelved.shelved_until, unshelved.state, unshelved.acked) == (None, "active", None)
        assert "UNSHELVE" not in await alarm_dialog(pilot)
        await pilot.press("escape", "escape", "q")
    assert app.return_code == 0


# -- the dashboard -------------------------------------------------------------------------------


@IN_BROWSER
async def test_the_dashboard_unshelves_a_shelved_alarm(dash: Dash) -> None:
    await live(dash)
    page = dash.page
    alarm = await estop_alarm(dash.rig)
    row = page.locator(f'#alarm-table tbody tr[data-alarm="{alarm.id}"]')
    await row.wait_for(timeout=SEEN_MS)
    unshelve = row.locator('button[data-method="alarms.unshelve"]')
    shelve = row.locator('button[data-method="alarms.shelve"]')
    await shelve.wait_for(timeout=SEEN_MS)
    assert await unshelve.count() == 0  # not shelved: nothing to unshelve
    await shelve.click()
    await dash.confirm()
    await row.locator(".alarm-state", has_text="shelved until").wait_for(timeout=SEEN_MS)
    await unshelve.wait_for(timeout=SEEN_MS)
    assert "unacked" not in (await row.get_attribute("class") or "")
    await dash.shot("alarm-shelved", "#attention")
    # Unshelve stops nothing: no confirmation; the alarm is shown as it is again at once.
    await unshelve.click()
    await unshelve.wait_for(state="detached", timeout=SEEN_MS)
    await page.locator("#alarm-message", has_text=f"alarm {alarm.id} unshelved").wait_for(
        timeout=SEEN_MS
    )
    await page.locator(f'#alarm-table tr.unacked[data-alarm="{alarm.id}"]').wait_for(
        timeout=SEEN_MS
    )
    assert "shelved" not in await row.locator(".alarm-state").inner_text()
    [listed] = [a for a in await dash.api("alarms.list") if a["id"] == alarm.id]
    assert listed["shelved_until"] is None and listed["state"] == "active"
