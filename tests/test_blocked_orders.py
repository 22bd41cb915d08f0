"""A blocked order (its route needs a machine out of service) says it is blocked and why, in
`cellctl orders`, the API's orders and status, and the console's board (issue 19, finding 10)."""

from __future__ import annotations

import shutil
from pathlib import Path

from rich.text import Text
from textual.widgets import Static

from cellctl.cell.blocked import blocked_reason
from cellctl.cell.config import load_cell
from cellctl.cell.journal import Part, open_journal
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.mailbox import open_mailbox
from cellctl.service.operator import list_orders
from cellctl.service.status import CellStatus
from cellctl.ui.console.widgets import board_text, shown
from tests.test_api import Api, api  # noqa: F401 (the fixture)


async def test_an_order_waiting_for_a_mill_out_of_service_says_so(api: Api) -> None:  # noqa: F811
    rig = api.rig
    await api.call("machines.out_of_service", {"machine": "cnc1", "reason": "new cutter"})
    await api.call("orders.submit", {"part_type": "wax-robot-base", "id": "B1"})
    await rig.wait_for(lambda: rig.journal.parts(order_id="B1"), "order B1 taken in")
    # Its only part waits at the conveyor for cnc1: the status says so, by field.
    status = CellStatus.model_validate(await api.call("cell.status"))
    order = next(o for o in status.orders if o.id == "B1")
    assert order.blocked.startswith("blocked:")
    assert "cnc1" in order.blocked and "new cutter" in order.blocked
    assert "cnc2" not in order.blocked  # its next move needs cnc1 (and the robot) only
    assert order.note.startswith(order.blocked)
    listed = next(o for o in await api.call("orders.list") if o["id"] == "B1")
    assert listed["blocked"] == order.blocked
    board = board_text(status, width=200).plain
    assert "BLOCKED its parts need cnc1, out of service" in board
    shown = await rig.cli("orders")
    assert shown.exit_code == 0, shown.output
    row = next(line for line in shown.output.splitlines() if " B1 " in line)
    assert "blocked" in row and "cnc1, out of service" in row
    # Back in service: the order goes on, and is no longer blocked.
    await api.call("machines.return_to_service", {"machine": "cnc1"})
    await rig.wait_for(lambda: rig.order_state("B1") == "done", "order B1 done", timeout=60)
    listed = next(o for o in await api.call("orders.list") if o["id"] == "B1")
    assert listed["blocked"] == ""


async def test_a_part_between_mills_is_blocked_by_the_next_one(api: Api) -> None:  # noqa: F811
    rig = api.rig
    await api.call("machines.out_of_service", {"machine": "cnc2", "reason": "spindle"})
    await api.call("orders.submit", {"part_type": "wax-robot-base", "id": "B2"})

    def cut_on_cnc1() -> bool:
        parts = rig.journal.parts(order_id="B2")
        return bool(parts) and parts[0].route_index == 1 and parts[0].status == "waiting"

    await rig.wait_for(cut_on_cnc1, "B2's part cut on cnc1, waiting for cnc2", timeout=60)
    listed = next(o for o in await api.call("orders.list") if o["id"] == "B2")
    assert "cnc2, out of service" in listed["blocked"] and "spindle" in listed["blocked"]
    assert "cnc1" not in listed["blocked"]


def test_a_part_whose_next_mill_holds_a_blocked_part_is_blocked_too() -> None:
    """Walkthrough: cnc2 out; P1-1, cut on cnc1, waits in cnc1 for cnc2; P1-2 waits at the
    conveyor for cnc1, which will not be free. The order is blocked, and says why."""
    config = load_cell(EXAMPLE_CELL)
    route = [step.mill for step in config.parts["wax-robot-base"].route]
    assert route[:2] == ["cnc1", "cnc2"]

    def part(n: int, index: int, location: str) -> Part:
        return Part(f"P1-{n}", "P1", "wax-robot-base", n, index, location, "waiting", 0.0)

    out = {"cnc2": "spindle"}
    stuck_in_cnc1 = [part(1, 1, "cnc1"), part(2, 0, "conveyor")]
    assert blocked_reason(config, "wax-robot-base", stuck_in_cnc1, out) == (
        "blocked: its parts need cnc2, out of service (spindle); cnc1 holds P1-1, which "
        "cannot leave"
    )
    # The first part not in a mill (the operator took it out): the second can go to cnc1.
    taken_out = [part(1, 1, "conveyor"), part(2, 0, "conveyor")]
    assert blocked_reason(config, "wax-robot-base", taken_out, out) == ""
    # Nothing out of service: nothing blocked.
    assert blocked_reason(config, "wax-robot-base", stuck_in_cnc1, {}) == ""


class _Counted(Static):
    """A Static that counts what it was given to show."""

    def __init__(self) -> None:
        super().__init__()
        self.updates: list[object] = []

    def update(self, content: object = "", **_: object) -> None:
        self.updates.append(content)


def test_a_console_widget_is_drawn_again_only_when_its_text_changed() -> None:
    widget = _Counted()
    drawn = shown(widget, Text("cnc1 Idle"), None)
    drawn = shown(widget, Text("cnc1 Idle"), drawn)  # the same status again: not drawn
    drawn = shown(widget, Text("cnc1 Idle", style="bold"), drawn)  # its look changed
    shown(widget, Text("cnc1 Busy"), drawn)
    assert [getattr(t, "plain", t) for t in widget.updates] == [
        "cnc1 Idle",
        "cnc1 Idle",
        "cnc1 Busy",
    ]


def test_an_order_held_by_a_stuck_doors_alarm_says_which_to_clear(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    config = load_cell(cell)
    with open_journal(cell) as journal, open_mailbox(cell) as mailbox:
        mailbox.post_order("wax-robot-base", 1, order_id="D1")
        [listed] = list_orders(mailbox, journal, config=config)
        assert listed["blocked"] == ""
        alarm, _ = journal.raise_alarm("plc", "interlock", "door of CNC 1 did not close")
        [listed] = list_orders(mailbox, journal, config=config)
        assert listed["blocked"] == (
            f"blocked: every transfer waits until alarm {alarm.id} is cleared "
            "(door of CNC 1 did not close)"
        )
        assert listed["note"].startswith(listed["blocked"])
        journal.clear_alarm(alarm.id, by="operator")
        [listed] = list_orders(mailbox, journal, config=config)
        assert listed["blocked"] == ""
