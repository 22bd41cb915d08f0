"""A due time where an operator posts an order or watches orders: the console's SUBMIT ORDER
(Textual's Pilot at 80x24, on the cell's files: a due time refused in the API's words with
the Due field selected, an order posted with one and shown on the board, an order the API
refuses asked again with the answers kept), ``cellctl run``'s live view (an order due, then
LATE as the cell's clock passes its due time, on virtual time), and the What-if form's
words for an order added with a due time.
The dashboard's order form: test_due_forms_dashboard.py."""

from __future__ import annotations

import io
import math
from datetime import datetime, timedelta

import pytest
from rich.console import Console
from textual.widgets import Input

from cellctl.clock import current_clock
from cellctl.testing.rig import CellRig
from cellctl.ui.console.app import ConsoleApp
from cellctl.ui.live_view import LiveView
from tests.test_console import SIZE, fill, rig, standalone_client, wait_text
from tests.test_due_live import backlog, line_of, shown

__all__ = ["rig"]  # the fixture, used by name


def weekday_ahead(days: int = 3) -> tuple[str, float]:
    """A due time as an operator types it, ``TUE 18:00`` (the weekday ``days`` ahead: the
    next such time is that day), and the moment it names, as unix seconds."""
    day = datetime.now() + timedelta(days=days)
    moment = day.replace(hour=18, minute=0, second=0, microsecond=0)
    name = ("MON", "TUE", "WED", "THU", "FRI", "SAT", "SUN")[moment.weekday()]  # any locale
    return f"{name} 18:00", moment.timestamp()


def focused(app: ConsoleApp) -> str | None:
    """The id of the field the cursor is in (what the operator's next keys go to)."""
    return app.focused.id if isinstance(app.focused, Input) else None


async def test_the_consoles_order_takes_a_due_time(rig: CellRig) -> None:
    """CELL -> SUBMIT ORDER: a due time the cell cannot read is refused in the form, in the
    API's words, nothing posted, Due selected and kept; a weekday and time posts the order
    due then, shown on the board; the same id again for another order is the API's refusal:
    the form again, its answers kept; a time already past posts an order LATE at once.
    WHAT IF's form says how an order to add takes a due time."""
    text, due = weekday_ahead()
    past_text, past = backlog()
    app = ConsoleApp(rig.directory, standalone_client(rig), traffic_period=0.1)
    async with app.run_test(size=SIZE) as pilot:
        await wait_text(pilot, "MAIN MENU")
        await pilot.press("c")
        await wait_text(pilot, "2. SUBMIT ORDER", "9. WHAT IF")
        await pilot.press("2")
        await wait_text(pilot, "SUBMIT ORDER", "Due (optional):", "due: FRI 18:00 or 18:00")
        await fill(pilot, "#id", "D1")
        await fill(pilot, "#due", "FRI 25:00")
        await pilot.press("enter")
        await wait_text(pilot, "due: time 'FRI 25:00': hours 0-23, minutes 0-59")
        assert focused(app) == "due"  # not Priority, whose 0 the words hold
        assert app.screen.query_one("#due", Input).value == "FRI 25:00"
        assert rig.mailbox.orders() == []
        await fill(pilot, "#due", text)
        await pilot.press("enter")
        said = await wait_text(pilot, "order D1 posted")
        assert f"due {datetime.fromtimestamp(due):%a %Y-%m-%d %H:%M:%S}" in said, said
        board = await wait_text(pilot, f"due {shown(due)}")
        assert "LATE" not in board, board
        assert rig.mailbox.due_times() == {"D1": due}

        # The same id for another order: only the cell knows; the form comes back with it.
        await pilot.press("2")
        await wait_text(pilot, "Due (optional):")
        await fill(pilot, "#id", "D1")
        await fill(pilot, "#due", past_text)
        await pilot.press("enter")
        await wait_text(pilot, "order D1 was posted before as", "Due (optional):")
        assert app.screen.query_one("#due", Input).value == past_text
        assert focused(app) == "id"
        await fill(pilot, "#id", "D2")
        await pilot.press("enter")
        await wait_text(pilot, "order D2 posted", "already past: the order is late")
        board = await wait_text(pilot, f"due {shown(past)} LATE")
        assert rig.mailbox.due_times() == {"D1": due, "D2": past}

        # CELL -> ORDERS lists both, LATE on the one past its due time.
        await pilot.press("1")
        listed = await wait_text(pilot, "ORDERS (live)", "D2 wax-robot-base")
        assert f"due {shown(past)} LATE" in line_of(listed, "D2 wax-robot-base"), listed
        assert "LATE" not in line_of(listed, "D1 wax-robot-base"), listed
        await pilot.press("escape")
        # WHAT IF's form shows how an order to add takes a due time.
        await pilot.press("9")
        await wait_text(pilot, "add orders: PART:QTY[@PRIORITY][ by WHEN] (several: , between)")
        await pilot.press("escape", "escape", "q")


# -- cellctl run's live view ------------------------------------------------------------------


def row_of(screen: str, order_id: str) -> str:
    """The live view's orders row of ``order_id``."""
    return next(line for line in screen.splitlines() if f"│ {order_id} " in line)


def rendered(view: LiveView, width: int = 120) -> str:
    """The live view as a terminal ``width`` columns wide shows it, as plain text."""
    console = Console(width=width, height=50, record=True, file=io.StringIO())
    console.print(view.render(console))
    return console.export_text()


@pytest.mark.virtual
async def test_run_live_view_shows_due_times_and_late(rig: CellRig) -> None:
    """On virtual time (no load can make it late): the orders table of ``cellctl run``'s
    live view shows each order's due time as ``cellctl orders`` does, none for an order
    without one, and LATE once the cell's clock passes an order's due time."""
    controller = await rig.start_controller()
    controller.pause()  # the orders stay open, as they are put
    clock = current_clock()
    due = (math.floor(clock.now() / 60) + 2) * 60.0
    rig.mailbox.post_order("wax-robot-base", 1, order_id="S1", due=due)
    rig.mailbox.post_order("wax-robot-base", 1, order_id="N1")
    view = LiveView(controller, rig.directory)
    words = f"{datetime.fromtimestamp(due):%Y-%m-%d %H:%M:%S}"

    def showing(*texts: str) -> str | None:
        """The view, once every order is in it and its S1 row holds ``texts``."""
        screen = rendered(view)
        if "│ N1 " not in screen or "│ S1 " not in screen:
            return None
        return screen if all(t in row_of(screen, "S1") for t in texts) else None

    screen = await rig.wait_for(showing, "the orders")
    assert words in row_of(screen, "S1") and "LATE" not in row_of(screen, "S1"), screen
    header = next(line for line in screen.splitlines() if "┃ order " in line)
    assert header.split("┃")[-2].strip() == "due", header
    assert words not in row_of(screen, "N1"), screen
    # Past its due time on the cell's clock (virtual: the loop jumps there), nothing else done.
    await clock.sleep(due - clock.now() + 1.0)
    late = await rig.wait_for(lambda: showing("LATE"), "S1 late")
    assert f"{words} LATE" in row_of(late, "S1"), late
    assert "LATE" not in row_of(late, "N1"), late
    # At 80 columns the due time and LATE are still shown whole (the cells wrap, never cut).
    narrow = rendered(view, 80)
    assert words in narrow and "LATE" in narrow, narrow
