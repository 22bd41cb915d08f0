"""``cellctl console``: the source's menu program on a live screen.

Three levels as in the source: the main menu (one entry per machine, then EXIT, numbered as
the source numbers them; the cell's own menu on ``c``), a machine's menu (the source's
functions by number, the tool-kit's extras by letter, the service toggle on ``s``) and the
parameter dialogs. The board (machines, alarms, orders), the last result and the selected
machine's traffic (the operator's own command first) stay on screen, updated live::

    app = ConsoleApp(Path("cell"), client)   # client from open_console_cell, or None
    await app.run_async()                    # the app opens the cell itself when None

Every action goes through the client (the controller's API when one runs, the machines'
own links otherwise); calls run in workers so the screen stays live during a download.

On a directory that is no cell (no cell.toml) but where a server runs (a shop's DNC server),
the console attaches to that server's API: its machines are those of its status, each
machine's menu is what the server declares (:mod:`.served`), and there is no CELL menu and
no service toggle (nothing dispatches work there).
"""

from __future__ import annotations

import contextlib
from datetime import datetime
from pathlib import Path
from typing import Any, ClassVar, TypeVar, cast

from rich.text import Text
from textual import events, on
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal
from textual.css.query import NoMatches
from textual.screen import ModalScreen, Screen
from textual.widgets import Footer, OptionList, Static
from textual.widgets.option_list import Option
from textual.worker import Worker

from cellctl.cell.owner import controller_holder
from cellctl.clock import current_clock
from cellctl.errors import CellctlError, UsageError
from cellctl.service.client import PLAN_SILENCE_S, CellClient, RemoteCell, attach
from cellctl.service.functions import MachineFunction, menu
from cellctl.service.methods import METHODS
from cellctl.service.status import StepInfo, StepKind, apply_update_json
from cellctl.ui.console.actions import console_actions, role_refusal
from cellctl.ui.console.cellmenu import CellActions
from cellctl.ui.console.dialogs import ConfirmDialog, Dialog, FormDialog, ParamsDialog
from cellctl.ui.console.entry import Action, Entry
from cellctl.ui.console.results import result_lines
from cellctl.ui.console.served import ServedFunction, ServedMenu, served_functions
from cellctl.ui.console.session import (
    ConsoleMachine,
    cell_machines,
    check_params,
    is_cell,
    open_console_cell,
    status_machines,
)
from cellctl.ui.console.traffic import Commands, traffic_rows
from cellctl.ui.console.widgets import Board, ResultPane, TrafficPane, header_text, shown, step_text

#: Seconds between two looks at the selected machine's traffic.
TRAFFIC_PERIOD = 0.5
#: Seconds between two tries to attach again once the controller's API closed.
REATTACH_S = 2.0
#: Seconds a manual function waits for the step in flight on a machine just taken out of
#: automatic service (then the controller's refusal is shown).
STEP_WAIT = 300.0
#: Parameters a dialog asks for (the rest keep their defaults).
DIALOG_FIELDS = ("partition", "program", "force", "input", "on")
#: Progress fields of the functions' progress dicts: (done, total).
PROGRESS_FIELDS = (("records", "records_total"), ("lines", "lines_total"))

#: Every acting API method the console offers (see :mod:`cellctl.ui.console.actions`).
CONSOLE_ACTIONS = console_actions()
#: The longest reason the console takes (an out-of-service or emergency stop's): the API's.
REASON_LENGTH: int = next(
    m.max_length
    for m in METHODS["cell.estop"].params.model_fields["reason"].metadata
    if hasattr(m, "max_length")
)
#: A machine menu's ``s`` entry: taking it out of service (False) or back (True).
SERVICE_LABELS = {False: "OUT OF SERVICE", True: "RETURN TO SERVICE"}
#: The main menu's key of the CELL menu (the source's numbers are the machines', then EXIT).
CELL_KEY = "c"
#: How the menus show what needs a controller when none runs.
UNAVAILABLE = "unavailable"
NO_CONTROLLER = "no controller runs on this cell (start `cellctl run` for that)"

T = TypeVar("T")


class ConsoleApp(App[None]):
    """The operator console (see the module docstring)."""

    TITLE = "cellctl console"
    CSS = """
    #header { height: auto; max-height: 3; background: $primary; color: $text; padding: 0 1; }
    #body { height: 1fr; }
    #menu { width: 36; height: 100%; border: none; border-top: solid $accent; padding: 0; }
    #board { width: 1fr; height: 100%; border: none; border-top: solid $secondary;
             border-left: solid $secondary; padding: 0 1; }
    ResultPane { height: auto; max-height: 7; padding: 0 1; }  /* widgets.RESULT_ROWS */
    #result-text { height: auto; }
    TrafficPane { height: 5; border-top: solid $secondary; padding: 0 1; }
    """
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("escape", "up", "Back"),
        Binding("q", "quit", "Quit"),
        # What a terminal's program does on Ctrl-C (Textual's own says how to quit instead).
        Binding("ctrl+c", "interrupt", "Quit", show=False, priority=True),
    ]

    def __init__(
        self,
        directory: Path,
        client: CellClient | None = None,
        *,
        traffic_period: float = TRAFFIC_PERIOD,
        plan_silence_s: float = PLAN_SILENCE_S,  # WHAT IF's (service.client.plan_call)
    ) -> None:
        super().__init__()
        self.directory = directory
        self.client: CellClient | None = client
        self.traffic_period = traffic_period
        self._header: Text | None = None  # what the header shows
        self.machines: list[ConsoleMachine] = []
        self.snapshot: dict[str, Any] = {}
        self.level: str = "main"  # "main", "cell" or a machine's name
        self.selected: str = ""  # whose traffic is shown
        self.entries: list[Entry] = []
        self.cell_actions = CellActions(self, plan_silence_s)
        self.served_menu = ServedMenu(self)
        #: Each machine's functions as its server declares them (none for a cell's).
        self.served: dict[str, list[ServedFunction]] = {}
        self.is_cell = is_cell(directory)
        self._traffic_busy = False
        #: Per machine, the operator's last command: when it was given (then, for a served
        #: function, the span until its answer), then its first row sent (the traffic pane
        #: shows it first).
        self.commands: Commands = {}
        self._closed = False
        self._reattaching = False
        self._reattach_tried = float("-inf")
        self.startup_error: CellctlError | None = None

    # -- layout and start ------------------------------------------------------------------

    def compose(self) -> ComposeResult:
        yield Static("cellctl console", id="header")
        with Horizontal(id="body"):
            yield OptionList(id="menu", markup=False)
            yield Board(id="board")
        yield ResultPane()
        yield TrafficPane()
        yield Footer()

    async def on_mount(self) -> None:
        try:
            if self.is_cell:
                self.machines = cell_machines(self.directory)
            if self.client is None:
                self.client = await open_console_cell(self.directory)
            self.snapshot = await self.client.subscribe(self._cell_changed)
            self.served = await served_functions(self.client)
            if not self.is_cell:
                self.machines = status_machines(self.snapshot)
                if not self.machines:
                    raise UsageError(f"the server on {self.directory} shows no machine")
        except CellctlError as e:
            self.startup_error = e
            await self.action_quit()
            return
        board = self.query_one("#board", Board)
        board.border_title = "cell" if self.is_cell else self.snapshot.get("cell", {}).get("name")
        self.selected = self.machines[0].name
        self._show_snapshot()
        self.show_menu("main")
        self.say(["Choose with the number keys, or the arrows and Enter."])
        self.set_interval(self.traffic_period, self._poll_traffic)
        # A cut's progress moves with the clock between updates (its estimate): redraw.
        self.set_interval(1.0, self._redraw_progress)

    @property
    def mode(self) -> str:
        return self.client.mode if self.client is not None else ""

    def mode_text(self) -> str:
        """What the header says of the console's mode."""
        if isinstance(self.client, RemoteCell) and self.client.closed.is_set():
            return "DISCONNECTED: controller's API closed; attaching again when it runs (q quits)"
        if self.mode == "attached":
            cell = self.snapshot.get("cell", {})
            server = "cellctl run" if self.is_cell else cell.get("name", "the server")
            return f"attached to {server} (pid {cell.get('pid', '?')})"
        return "standalone: links held by this console"

    # -- live status ------------------------------------------------------------------------

    def _cell_changed(self, changes: dict[str, Any]) -> None:
        # Called from the client's own task: apply the changes in the app's.
        if not self._closed:
            self.call_later(self._apply_changes, changes)

    def _apply_changes(self, changes: dict[str, Any]) -> None:
        if self._closed:
            return
        self.snapshot = apply_update_json(self.snapshot, changes)
        self._show_snapshot()
        if self.level != "main":
            # An update as the console exits another way than its quit (its widgets going,
            # the client not closed yet) has no menu left to refresh: see _show_snapshot.
            with contextlib.suppress(NoMatches):
                self.show_menu(self.level, keep=True)

    def _redraw_progress(self) -> None:
        machines = self.snapshot.get("machines", {}).values()
        if not self._closed and any((m.get("progress") or {}).get("running") for m in machines):
            with contextlib.suppress(NoMatches):  # exiting: see _show_snapshot
                self.query_one("#board", Board).show(self.snapshot)

    def _show_snapshot(self) -> None:
        paused = "  CELL PAUSED" if self.snapshot.get("cell", {}).get("paused") else ""
        where = "cell" if self.is_cell else "directory"
        try:
            widget = self.query_one("#header", Static)
            width = widget.content_size.width or self.size.width - 2
            header = header_text(f"{self.mode_text()}{paused}", where, str(self.directory), width)
            self._header = shown(widget, Text(header), self._header)
            self.query_one("#board", Board).show(self.snapshot)
        except NoMatches:
            # An update that came as the console exits another way than its quit (its
            # widgets already gone, the client not closed yet): nothing left to draw on.
            return

    def on_resize(self) -> None:
        self._show_snapshot()  # the header fits the terminal's width

    def in_service(self, name: str) -> bool:
        machine = self.snapshot.get("machines", {}).get(name, {})
        return self.mode == "attached" and bool(machine.get("in_service"))

    def _poll_traffic(self) -> None:
        if isinstance(self.client, RemoteCell) and self.client.closed.is_set():
            self._show_snapshot()  # the header says so
            self.query_one(TrafficPane).disconnected(self.selected)
            now = current_clock().monotonic()
            if (
                not self._closed
                and not self._reattaching
                and now - self._reattach_tried > REATTACH_S
            ):
                self._reattaching, self._reattach_tried = True, now
                _again: Worker[None] = self.run_worker(
                    self._reattach, group="reattach", exit_on_error=False
                )
            return
        if self._traffic_busy or self._closed or self.client is None or not self.selected:
            return
        self._traffic_busy = True
        # The method, not a coroutine (none left unawaited if the app exits); typed for mypy.
        _worker: Worker[None] = self.run_worker(
            self._traffic_of_selected, group="traffic", exit_on_error=False
        )

    async def _reattach(self) -> None:
        """Attach to the controller again once one runs on the directory (a restarted
        ``cellctl run``, a restarted service): the board and the menus go on live."""
        try:
            if controller_holder(self.directory) is None:
                return  # none runs yet: the next look tries again
            client = await attach(self.directory)
            try:
                snapshot = await client.subscribe(self._cell_changed)
            except CellctlError:
                await client.close()
                raise
        except (CellctlError, OSError):
            return
        finally:
            self._reattaching = False
        old, self.client, self.snapshot = self.client, client, snapshot
        if old is not None:
            with contextlib.suppress(CellctlError, OSError):
                await old.close()
        if self._closed:
            await client.close()
            return
        self._show_snapshot()
        when = datetime.fromtimestamp(current_clock().now())
        self.say([f"attached again to the controller at {when:%H:%M:%S}"])

    async def _traffic_of_selected(self) -> None:
        await self._traffic(self.selected)

    async def _traffic(self, name: str) -> None:
        pane = self.query_one(TrafficPane)
        try:
            assert self.client is not None
            pane.show(name, *await traffic_rows(self.client, name, self.commands))
        except CellctlError as e:
            pane.border_title = f"traffic: {name}"
            pane.show_text(Text(str(e)))
        finally:
            self._traffic_busy = False

    # -- menus ------------------------------------------------------------------------------

    def main_entries(self) -> list[Entry]:
        entries = [
            Entry(str(i), f"{m.title} ({m.name})", self._open(m.name))
            for i, m in enumerate(self.machines, start=1)
        ]
        # The source's numbers: the machines, then EXIT. The cell has a letter of its own.
        entries.append(Entry(str(len(entries) + 1), "EXIT", self._exit_action))
        if self.is_cell:
            entries.append(Entry(CELL_KEY, "CELL (orders, parts, alarms)", self._open("cell")))
        return entries

    def machine_entries(self, machine: ConsoleMachine) -> list[Entry]:
        served = self.served.get(machine.name)
        if served is not None:
            return self.served_menu.entries(machine, served)
        entries: list[Entry] = []
        letters = iter("abcdefgh")
        functions = menu(machine.family, machine.kind)
        for fn in functions:
            key = str(fn.menu) if fn.menu is not None else next(letters)
            entries.append(Entry(key, fn.label, self._function(machine, fn)))
        last = max(fn.menu or 0 for fn in functions) + 1
        entries.insert(last - 1, Entry(str(last), "EXIT", self._back_action))
        # A server's own machines (no cell) take no work from a cell: no service to toggle.
        if self.is_cell and self.mode == "attached":
            back = not self.in_service(machine.name)
            label = SERVICE_LABELS[back]
            entries.append(Entry("s", label, self._service(machine.name, back)))
        elif self.is_cell:
            entries.append(Entry("s", "SERVICE", None, UNAVAILABLE))
        return entries

    def machine(self, name: str) -> ConsoleMachine:
        return next(m for m in self.machines if m.name == name)

    def show_menu(self, level: str, *, keep: bool = False) -> None:
        """Show the main menu, the cell menu or a machine's menu."""
        if level == "main":
            entries, title = self.main_entries(), "MAIN MENU"
        elif level == "cell":
            entries, title = self.cell_actions.entries(), "CELL"
        else:
            machine = self.machine(level)
            entries, title = self.machine_entries(machine), f"{machine.title} ({machine.name})"
            self.selected = machine.name
        option_list = self.query_one("#menu", OptionList)
        if keep and [e.prompt() for e in entries] == [e.prompt() for e in self.entries]:
            self.entries = entries
            return
        highlighted = option_list.highlighted if keep else 0
        self.level = level
        self.entries = entries
        option_list.clear_options()
        option_list.add_options(
            Option(e.prompt(), id=e.key, disabled=e.action is None) for e in entries
        )
        option_list.border_title = title
        option_list.highlighted = highlighted
        option_list.focus()

    def _open(self, level: str) -> Action:
        async def action() -> None:
            self.show_menu(level)

        return action

    async def _back_action(self) -> None:
        self.action_up()

    async def _exit_action(self) -> None:
        self.call_later(self.action_quit)  # from the app's own task, not this worker

    def action_up(self) -> None:
        """Escape: up one level."""
        if self.level != "main" and isinstance(self.screen, Screen):
            self.show_menu("main")

    async def action_quit(self) -> None:
        """Quit, closing the client (a standalone console releases its links)."""
        if not self._closed:
            self._closed = True
            self.workers.cancel_all()
            if self.client is not None:
                with contextlib.suppress(CellctlError, OSError):
                    await self.client.close()
        self.exit()

    async def action_interrupt(self) -> None:
        """Ctrl-C: quit as ``q`` does, from a dialog too (it is cancelled: nothing is sent)."""
        await self.action_quit()

    def check_action(self, action: str, parameters: tuple[object, ...]) -> bool | None:
        # A dialog's own keys (y/n, typing a name with a q) must not quit the console.
        return not (action in ("quit", "up") and isinstance(self.screen, ModalScreen))

    def on_key(self, event: events.Key) -> None:
        if isinstance(self.screen, ModalScreen) or event.character is None:
            return
        key = event.character
        if key == "0" and self.level == "main":
            key = str(len(self.machines) + 1)  # 0 also leaves, as in the source
        for entry in self.entries:
            if entry.key == key:
                event.stop()
                self.choose(entry)
                return

    @on(OptionList.OptionSelected, "#menu")
    def _selected(self, event: OptionList.OptionSelected) -> None:
        for entry in self.entries:
            if entry.key == event.option.id:
                self.choose(entry)

    @on(OptionList.OptionHighlighted, "#menu")
    def _highlighted(self, event: OptionList.OptionHighlighted) -> None:
        # In the main menu, the highlighted machine's traffic is shown.
        if self.level == "main" and event.option.id is not None and event.option.id.isdigit():
            index = int(event.option.id) - 1
            if 0 <= index < len(self.machines):
                self.selected = self.machines[index].name

    def choose(self, entry: Entry) -> None:
        """Run a menu entry's action in a worker (it may wait for dialogs and long calls)."""
        if entry.action is None:
            self.say([f"{entry.label}: {entry.note}: {NO_CONTROLLER}"], "yellow")
            return
        self.run_worker(self._guarded(entry.action), group="action")

    async def _guarded(self, action: Action) -> None:
        try:
            await action()
        except CellctlError as e:
            self.say([f"error: {e}"], "red")
            self.query_one(ResultPane).progress(None, None)

    # -- results ----------------------------------------------------------------------------

    def say(self, lines: list[str], style: str = "") -> None:
        """Show the outcome of the last action."""
        self.query_one(ResultPane).say(lines, style)

    def show_progress(self, done: float | None, total: float | None) -> None:
        """The running call's progress bar (``total`` None hides it)."""
        self.query_one(ResultPane).progress(done, total)

    async def call(self, method: str, params: dict[str, Any]) -> Any:
        """A cell-level call; its result (a CellctlError is shown by the caller's guard).
        An acting method must be declared in :data:`CONSOLE_ACTIONS` (where it is)."""
        assert self.client is not None
        declared = method in CONSOLE_ACTIONS or not METHODS[method].acts
        assert declared, f"{method}: an action of the console missing in CONSOLE_ACTIONS"
        return await self.client.call(method, params)

    async def ask_reason(self, question: str, default: str) -> str | None:
        """``question`` with a reason to give (``default`` offered, selected); None: Escape."""

        def check(raw: dict[str, str]) -> dict[str, Any]:
            reason = raw["reason"].strip()
            if not reason:
                raise UsageError("give a reason (it goes into the journal and the alarm)")
            if len(reason) > REASON_LENGTH:
                raise UsageError(f"reason: at most {REASON_LENGTH} characters")
            return {"reason": reason}

        answer = await self.ask(FormDialog(question, [("reason", "Reason:", default)], check))
        return None if answer is None else str(answer["reason"])

    async def ask(self, dialog: Dialog[T]) -> T | None:
        """Show ``dialog`` and wait for its answer (None: cancelled); from a worker only."""
        return cast("T | None", await self.push_screen_wait(cast(Screen[Any], dialog)))

    async def confirm(self, question: str) -> bool:
        answer: bool | None = await self.ask(ConfirmDialog(question))
        return answer is True

    def _service(self, name: str, back: bool) -> Action:
        async def action() -> None:
            params: dict[str, Any] = {"machine": name}
            if back:
                question = f"Return {name} to automatic service? (initialized first if needed)"
                method = "machines.return_to_service"
                if not await self.confirm(question):
                    self.say([f"{name}: service unchanged"])
                    return
            else:
                question = (
                    f"Take {name} out of automatic service? No new work goes to it (its step "
                    "in flight finishes first); manual functions become possible. Why?"
                )
                method = "machines.out_of_service"
                reason = await self.ask_reason(question, "maintenance")
                if reason is None:
                    self.say([f"{name}: service unchanged"])
                    return
                params["reason"] = reason
            self.say([f"{name}: ..."])
            result = await self.call(method, params)
            self.say([result["message"]], "green")
            machine = self.snapshot.get("machines", {}).get(name)
            if machine is not None:
                machine["in_service"] = back  # until the next update says so
                self.show_menu(self.level, keep=True)

        return action

    async def step_ended(self, name: str, timeout: float = STEP_WAIT) -> None:
        """Wait (live) until the step in flight on ``name`` has ended, up to ``timeout``.

        Asked of the controller (``machines.list``), not read from the pushed status: an
        update may still be on its way, and a step it does not show yet must be waited for
        too (else the function is refused as the machine is still busy with it)."""
        assert self.client is not None
        clock = current_clock()
        deadline = clock.monotonic() + timeout
        while True:
            machines = await self.client.call("machines.list")
            step = machines.get(name, {}).get("step") or {}
            if not step or step.get("what") == StepKind.MANUAL or clock.monotonic() > deadline:
                return
            shown = step_text(StepInfo.model_validate(step))
            self.say([f"{name}: waiting for its step in flight to end ({shown})"], "yellow")
            await clock.sleep(0.1)

    # -- machine functions ------------------------------------------------------------------

    def _function(self, machine: ConsoleMachine, fn: MachineFunction) -> Action:
        async def action() -> None:
            await self.run_function(machine, fn)

        return action

    async def run_function(self, machine: ConsoleMachine, fn: MachineFunction) -> None:
        """Ask for the function's parameters, check them, take the machine out of automatic
        service if it must be (asking first), run it and show its outcome."""
        assert self.client is not None
        # A function its caller's role may not run is refused first: before a dialog, and
        # before its machine is taken out of automatic service for nothing. (Any role may
        # observe.)
        try:
            info = {} if fn.observes else await self.client.call("server.info")
        except CellctlError as e:
            self.say([f"{machine.name}: {fn.label}: {e}"], "red")
            return
        refused = role_refusal(info, f"{machine.family}.{fn.name}")
        if refused:
            self.say([f"{machine.name}: {fn.label}: {refused}; nothing was done"], "red")
            return
        params: dict[str, Any] = {}
        fields = [f for f in DIALOG_FIELDS if f in fn.params.model_fields]
        if fields:
            dialog = ParamsDialog(
                f"{machine.title} ({machine.name}): {fn.label}",
                fields,
                lambda raw: check_params(machine, fn, raw, self.directory),
                directory=self.directory,
                suffixes=machine.suffixes,
                program=(machine.setup or "") if fn.name == "init" else "",
            )
            answer = await self.ask(dialog)
            if answer is None:
                self.say([f"{machine.name}: {fn.label} cancelled"])
                return
            params = answer
        if not fn.observes and self.in_service(machine.name):
            question = (
                f"{machine.name} is in automatic service. Take it out of automatic service "
                f"to run {fn.label} by hand? (its step in flight finishes first)"
            )
            if not await self.confirm(question):
                self.say([f"{machine.name}: {fn.label} not run: it stays in automatic service"])
                return
            out = await self.call(
                "machines.out_of_service",
                {"machine": machine.name, "reason": f"{fn.label} by hand at the console"},
            )
            self.say([out["message"]])
            await self.step_ended(machine.name)
        pane = self.query_one(ResultPane)
        self.say([f"{machine.name}: {fn.label} ..."])
        self.commands[machine.name] = current_clock().now()  # traffic rows' wall time

        def progress(data: dict[str, Any]) -> None:
            for done, total in PROGRESS_FIELDS:
                if done in data and total in data:
                    pane.progress(data[done], data[total])
                    phase = data.get("phase", "")
                    self.say([f"{machine.name}: {fn.label} {phase} {data[done]}/{data[total]}"])

        try:
            result = await self.client.call(
                f"{machine.family}.{fn.name}", {"machine": machine.name, **params}, progress
            )
        except CellctlError as e:
            self.say([f"{machine.name}: {fn.label}: {e}"], "red")
            return
        finally:
            pane.progress(None, None)
        self.say(result_lines(machine.name, fn, result), "green")
