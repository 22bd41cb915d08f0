"""The console's CELL menu: orders (list, submit, cancel), alarms (list, acknowledge, shelve,
unshelve, clear), held parts (release, release with redo, scrap), pause/resume, the emergency
stop and WHAT IF (a plan of the cell ahead, :mod:`.whatif`).

Orders, alarms and parts work in both modes (on the cell's files when no controller runs);
pause, resume and the emergency stop need the controller and are shown as unavailable
without one.
"""

from __future__ import annotations

import asyncio
import re
from pathlib import Path
from typing import Any, Protocol, TypeVar

from cellctl.clock import current_clock
from cellctl.errors import MachineInUse, UsageError
from cellctl.service.client import PLAN_SILENCE_S, CellClient, own_session, plan_call
from cellctl.service.machines import load_cell_file
from cellctl.service.operator import scrap_question
from cellctl.service.orderdue import resolve_due
from cellctl.ui.alarm_marks import alarm_marks
from cellctl.ui.console.dialogs import Dialog, FormDialog, LivePickDialog, PickDialog
from cellctl.ui.console.entry import Entry
from cellctl.ui.console.whatif import (
    PlanProgress,
    PlanView,
    plan_params,
    plan_span,
    plan_text,
    refusal_field,
    summary,
)
from cellctl.ui.console.widgets import due_text

T = TypeVar("T")

#: SUBMIT ORDER's words for its due time (as ``cellctl submit --due`` takes it).
DUE_HINT = "due: FRI 18:00 or 18:00 (the next one), 2026-12-04T18:00; empty: none"
#: Order states an order may still be cancelled in.
NOT_STARTED = ["posted", "accepted"]
NO_CONTROLLER = "unavailable"


class ConsoleHost(Protocol):
    """What the CELL menu needs of the console app (:class:`~cellctl.ui.console.app.ConsoleApp`
    is one): its cell, its mode and snapshot, and a way to call, ask and say."""

    @property
    def directory(self) -> Path: ...

    @property
    def mode(self) -> str: ...

    @property
    def snapshot(self) -> dict[str, Any]: ...

    @property
    def client(self) -> CellClient | None: ...

    def action_up(self) -> None: ...

    def say(self, lines: list[str], style: str = "") -> None: ...

    def show_progress(self, done: float | None, total: float | None) -> None: ...

    async def call(self, method: str, params: dict[str, Any]) -> Any: ...

    async def ask(self, dialog: Dialog[T]) -> T | None: ...

    async def confirm(self, question: str) -> bool: ...

    async def ask_reason(self, question: str, default: str) -> str | None: ...


class CellActions:
    """The CELL menu's entries and what they do, on a console app (:class:`ConsoleHost`).
    ``plan_silence_s``: how long WHAT IF's plan may go unheard before it is given up."""

    def __init__(self, app: ConsoleHost, plan_silence_s: float = PLAN_SILENCE_S) -> None:
        self.app = app
        self.plan_silence_s = plan_silence_s
        self._playing: asyncio.Task[Any] | None = None  # WHAT IF's plan, while it plays

    def entries(self) -> list[Entry]:
        attached = self.app.mode == "attached"
        paused = bool(self.app.snapshot.get("cell", {}).get("paused"))
        note = "" if attached else NO_CONTROLLER
        return [
            Entry("1", "ORDERS", self.orders),
            Entry("2", "SUBMIT ORDER", self.submit),
            Entry("3", "CANCEL ORDER", self.cancel),
            Entry("4", "ALARMS", self.alarms),
            Entry("5", "HELD PARTS", self.held_parts),
            Entry(
                "6",
                "RESUME" if paused else "PAUSE",
                (self.resume if paused else self.pause) if attached else None,
                note,
            ),
            Entry("7", "EMERGENCY STOP", self.estop if attached else None, note),
            Entry("8", "EXIT", self.back),
            # After the menu's EXIT, as the machine menus' extras: 1-8 keep their numbers.
            Entry("9", "WHAT IF (plan ahead)", self.what_if),
        ]

    async def back(self) -> None:
        self.app.action_up()

    # -- orders -----------------------------------------------------------------------------

    async def orders(self) -> None:
        found: list[dict[str, Any]] = await self.app.call("orders.list", {})
        if not found:
            self.app.say(["no orders"])
            return

        async def fetch() -> list[tuple[str, str]]:
            # Live: the list follows the orders while it is open (states, parts, new ones).
            nonlocal found
            found = await self.app.call("orders.list", {})
            return [(o["id"], order_line(o)) for o in found]

        rows = [(o["id"], order_line(o)) for o in found]
        picked = await self.app.ask(
            LivePickDialog(
                "ORDERS (live)", rows, fetch, "Enter on an order not started offers to cancel it"
            )
        )
        order = next((o for o in found if o["id"] == picked), None)
        if order is not None and order["state"] in NOT_STARTED:
            await self._cancel(order["id"])
        elif order is not None:
            self.app.say([order_line(order)])

    async def submit(self) -> None:
        """Ask for an order (part type, quantity, priority, id, due time) and post it; a
        refusal (the form's check or the API's) asks again, the answers kept."""
        parts = load_cell_file(self.app.directory).get("parts")
        types = list(parts) if isinstance(parts, dict) else []
        values = {
            "part_type": types[0] if types else "",
            "qty": "1",
            "priority": "0",
            "id": "",
            "due": "",
        }

        def check(raw: dict[str, str]) -> dict[str, Any]:
            values.update(raw)
            return order_params(raw, types)

        known = f" ({', '.join(types)})" if types else ""
        title = f"SUBMIT ORDER{known}\n{DUE_HINT}"
        problems = ""
        while True:
            fields = [
                ("part_type", "Part type:", values["part_type"]),
                ("qty", "Quantity:", values["qty"]),
                ("priority", "Priority:", values["priority"]),
                ("id", "Order id (optional):", values["id"]),
                ("due", "Due (optional):", values["due"]),
            ]
            form = FormDialog(title, fields, check, problems, field_of=order_field)
            answer = await self.app.ask(form)
            if answer is None:
                self.app.say(["order not submitted"])
                return
            try:
                result = await self.app.call("orders.submit", answer)
            except UsageError as e:
                # What only the cell judges (its clock, its part types, an id posted before):
                # the form again with the answers and the API's words, as WHAT IF does.
                problems = str(e)
                self.app.say([f"order refused: {problems}"], "red")
                continue
            self.app.say([result["message"]], "green")
            return

    async def cancel(self) -> None:
        found: list[dict[str, Any]] = await self.app.call("orders.list", {"states": NOT_STARTED})
        if not found:
            self.app.say(["no order that has not started"])
            return
        picked = await self.app.ask(
            PickDialog("CANCEL ORDER", [(o["id"], order_line(o)) for o in found])
        )
        if picked is not None:
            await self._cancel(picked)

    async def _cancel(self, order_id: str) -> None:
        if not await self.app.confirm(f"Cancel order {order_id}?"):
            self.app.say([f"order {order_id} not cancelled"])
            return
        result = await self.app.call("orders.cancel", {"id": order_id})
        self.app.say([result["message"]], "green")

    # -- alarms and parts -------------------------------------------------------------------

    async def alarms(self) -> None:
        found: list[dict[str, Any]] = await self.app.call("alarms.list", {})
        if not found:
            self.app.say(["no open alarm"])
            return
        now = current_clock().now()
        rows = [(str(a["id"]), f"{a['id']} {alarm_line(a, now)}") for a in found]
        hint = "Enter on an alarm offers to acknowledge, shelve, unshelve, clear it"
        picked = await self.app.ask(PickDialog("ALARMS", rows, hint))
        if picked is None:
            return
        choices = [
            ("ack", "1. ACKNOWLEDGE (seen; it stays open)"),
            ("shelve", "2. SHELVE FOR 1 HOUR"),
            ("clear", "3. CLEAR (its cause is dealt with)"),
        ]
        # Offered for a shelved alarm only (as the dashboard's Unshelve), by its own number.
        if any(str(a["id"]) == picked and shelved(a, now) for a in found):
            choices.append(("unshelve", "4. UNSHELVE (show it again now)"))
        what = await self.app.ask(PickDialog(f"ALARM {picked}", choices))
        if what == "ack":
            result = await self.app.call("alarms.ack", {"id": int(picked)})
        elif what == "shelve":
            result = await self.app.call("alarms.shelve", {"id": int(picked), "seconds": 3600})
        elif what == "unshelve":
            result = await self.app.call("alarms.unshelve", {"id": int(picked)})
        elif what == "clear":
            if not await self.app.confirm(f"Clear alarm {picked}? (its cause is dealt with)"):
                self.app.say([f"alarm {picked} not cleared"])
                return
            result = await self.app.call("alarms.clear", {"id": int(picked)})
        else:
            return
        self.app.say([result["message"]], "green")

    async def held_parts(self) -> None:
        found: list[dict[str, Any]] = await self.app.call("parts.list", {"statuses": ["held"]})
        if not found:
            self.app.say(["no held part"])
            return
        rows = [
            (p["id"], f"{p['id']} {p['part_type']} at {p['location']}: {p.get('note', '')}")
            for p in found
        ]
        picked = await self.app.ask(PickDialog("HELD PARTS", rows))
        if picked is None:
            return
        what = await self.app.ask(
            PickDialog(
                f"PART {picked}",
                [
                    ("release", "1. RELEASE (continue its route)"),
                    ("redo", "2. RELEASE WITH REDO (cut its step again)"),
                    ("scrap", "3. SCRAP"),
                ],
            )
        )
        if what == "scrap":
            places = next((list(p.get("may_be_in", [])) for p in found if p["id"] == picked), [])
            if not await self.app.confirm(scrap_question(picked, places)):
                self.app.say([f"part {picked} kept"])
                return
            # Asked about those machines by name: the answer is the API's taken_out.
            params = {"id": picked, "taken_out": bool(places)}
            result = await self.app.call("parts.scrap", params)
        elif what in ("release", "redo"):
            result = await self.app.call("parts.release", {"id": picked, "redo": what == "redo"})
        else:
            return
        self.app.say([result["message"]], "green")

    # -- what if ------------------------------------------------------------------------------

    async def what_if(self) -> None:
        """Ask for a plan's inputs, play it through ``plan.run`` (the menu's worker waits;
        the board stays live) and show it; a refusal (the parsers' or the API's) asks again.
        Chosen while its plan plays: offers to stop it."""
        from cellctl.plan.engine import POLICIES
        from cellctl.plan.when import PLAN_POLL_S

        if self._playing is not None:
            question = "WHAT IF: a plan is playing. Stop it? (y stops it, n lets it play on)"
            if await self.app.confirm(question) and self._playing is not None:
                self._playing.cancel()
            return
        values = {
            "horizon": "8h",
            "fault": "",
            "add": "",
            "policy": "default",
            "poll": "",
            "seed": "",
        }
        problems = ""
        while True:
            fields = [
                ("horizon", "Horizon:", values["horizon"]),
                ("fault", "Faults:", values["fault"]),
                ("add", "Add orders:", values["add"]),
                ("policy", "Policy:", values["policy"]),
                ("poll", "Poll (s):", values["poll"]),
                ("seed", "Seed:", values["seed"]),
            ]

            def check(raw: dict[str, str]) -> dict[str, Any]:
                values.update(raw)
                return plan_params(raw, current_clock().now())

            title = (
                "WHAT IF: the cell played ahead on a copy\n"
                "horizon: a span (8h, 90m) or a time (FRI 18:00, 18:00)\n"
                "faults: cnc2:down@10:00-11:00 (several: ; between)\n"
                "add orders: PART:QTY[@PRIORITY][ by WHEN] (several: , between)\n"
                f"policy: {', '.join(POLICIES)}; A,B or all to compare\n"
                f"poll: s between looks at idle machines (empty: {PLAN_POLL_S:g})\n"
                "seed: of anything random in the machines, as a noise fault (empty: 0)"
            )
            form = FormDialog(title, fields, check, problems, field_of=refusal_field)
            params = await self.app.ask(form)
            if params is None:
                self.app.say(["no plan"])
                return
            self.app.say(["planning... (the cell played ahead on a copy; it goes on)"], "yellow")
            try:
                answer = await self._played(params)
            except (UsageError, MachineInUse) as e:  # MachineInUse: another plan plays
                problems = str(e)
                self.app.say([f"plan refused: {e}"], "red")
                continue
            break
        if answer is None:
            self.app.say(["plan stopped: its play ended (9 again plans anew)"], "yellow")
            return
        self.app.say([summary(answer, self.app.directory)], "green")
        await self.app.ask(PlanView("WHAT IF", plan_text(answer, self.app.directory)))

    async def _played(self, params: dict[str, Any]) -> Any:
        """``params``' plan, waited for as ``cellctl plan`` waits (while its play tells how
        far it has gone: :func:`~cellctl.service.client.plan_call`), on a session of its own
        (given up or stopped, its play ends); how far on the result line. None: stopped."""
        from cellctl.plan.spec import policies_of

        assert self.app.client is not None
        client = self.app.client
        shown = PlanProgress(len(policies_of(str(params.get("policy", "default")))))
        span_s = plan_span(params, current_clock().now())

        def told(data: dict[str, Any]) -> None:
            shown.told(data)
            self.app.say([f"planning... {shown.text()}"], "yellow")
            self.app.show_progress(100 * shown.fraction(), 100)

        async def play() -> Any:
            async with own_session(client) as cell:
                return await plan_call(cell, params, span_s, told, silence_s=self.plan_silence_s)

        self._playing = asyncio.create_task(play())
        try:
            return await self._playing
        except asyncio.CancelledError:
            this = asyncio.current_task()
            if this is not None and this.cancelling():
                raise  # the console quits: the plan's task was cancelled with this one
            return None  # stopped from the menu
        finally:
            self._playing = None
            self.app.show_progress(None, None)

    # -- the controller ---------------------------------------------------------------------

    async def pause(self) -> None:
        result = await self.app.call("cell.pause", {})
        self.app.say([result["message"]], "green")

    async def resume(self) -> None:
        result = await self.app.call("cell.resume", {})
        self.app.say([result["message"]], "green")

    async def estop(self) -> None:
        question = (
            "EMERGENCY STOP: stop the robot, halt the mills, hold the parts in work? "
            "Enter stops, Escape does not."
        )
        reason = await self.app.ask_reason(question, "operator console")
        if reason is None:
            self.app.say(["no emergency stop"])
            return
        result = await self.app.call("cell.estop", {"reason": reason})
        self.app.say([result["message"]], "red")


#: The SUBMIT ORDER field a refusal names, by its words (the form's and the API's): an id
#: posted before for another order, the part type, quantity, priority, due time.
ORDER_FIELDS = (
    ("id", r"\border \S+ was posted before as\b"),
    ("part_type", r"\bpart[ _]type\b"),
    ("qty", r"\bqty\b"),
    ("priority", r"\bpriority\b"),
    ("due", r"\bdue\b"),
)


def order_field(words: str) -> str | None:
    """The SUBMIT ORDER field ``words`` (a refusal) name first; None if none. The dialog
    selects it: a due time refused selects Due, never a field whose value the words
    happen to hold (``0`` in ``hours 0-23``)."""
    found = [
        (m.start(), field) for field, pattern in ORDER_FIELDS if (m := re.search(pattern, words))
    ]
    return min(found)[1] if found else None


def order_params(raw: dict[str, str], types: list[str]) -> dict[str, Any]:
    """SUBMIT ORDER's answers as ``orders.submit``'s parameters, checked before anything is
    sent (``types``: cell.toml's part types, [] for unknown); UsageError listing every
    problem, each naming its field. The due time goes as typed: the cell reads it again on
    its own clock, as for ``cellctl submit --due``."""
    problems = []
    part_type = raw["part_type"].strip()
    if types and part_type not in types:
        problems.append(f"unknown part type {part_type!r} (known: {', '.join(types)})")
    for key in ("qty", "priority"):
        try:
            int(raw[key])
        except ValueError:
            problems.append(f"{key} must be a whole number, not {raw[key]!r}")
    if not problems and int(raw["qty"]) < 1:
        problems.append("qty must be at least 1")
    due = raw.get("due", "").strip()
    if due:
        try:
            resolve_due(due, current_clock().now())
        except UsageError as e:  # in the API's words for its due parameter
            problems.append(f"due: {e}")
    if problems:
        raise UsageError("\n".join(problems))
    params: dict[str, Any] = {
        "part_type": part_type,
        "qty": int(raw["qty"]),
        "priority": int(raw["priority"]),
    }
    if raw["id"].strip():
        params["id"] = raw["id"].strip()
    if due:
        params["due"] = due
    return params


def alarm_line(a: dict[str, Any], now: float) -> str:
    """An open alarm in one line: priority, machine, code, text, and UNACKED/acked,
    RTN (returned to normal), SHELVED."""
    marks = alarm_marks(
        acked=a.get("acked"),
        returned=a.get("returned"),
        shelved_until=a.get("shelved_until"),
        now=now,
    )
    return f"{a['machine']} {a['code']}: {a['text']} [{a.get('priority', '')} {marks}]"


def shelved(a: dict[str, Any], now: float) -> bool:
    """True while alarm ``a`` (as the API gives it) is shelved at ``now``."""
    return bool((a.get("shelved_until") or 0) > now)


def order_line(order: dict[str, Any]) -> str:
    """An order as ``orders.list`` gives it, on one line: ``L1 wax-robot-base x1 p0 posted
    waiting 1 due Fri 11-27 18:00 LATE -- blocked: ...``."""
    parts = " ".join(f"{k} {v}" for k, v in sorted(order.get("parts", {}).items()))
    # .get: a controller of an older cellctl answers without due times.
    due = due_text(order.get("due"), bool(order.get("late")))
    return (
        f"{order['id']} {order['part_type']} x{order['qty']} p{order['priority']} "
        f"{order['state']} {parts} {due}".rstrip()
    ) + (f" -- {order['blocked']}" if order.get("blocked") else "")
