"""Machine menus a server declares itself (``machines.functions``): for a server that is not a
cell's controller (a shop's DNC server), what an operator may do to each of its machines, as
menu lines of the console. The console knows no kind here: it shows the server's labels, asks
for what each one asks (a program file), and calls its method through the API, with the
caller's token and role like every other call::

    served = await served_functions(client)     # {"mill1": [ServedFunction(...)], ...}; {}: none
    menu = ServedMenu(app)
    entries = menu.entries(machine, served["mill1"])   # 1 READ IN ... then EXIT

A program is read here (relative to the directory, and only within it: a path, a ``..`` or
a symlink leading out is refused before anything is read) and sent as its name and text; the
server checks it with the machine's own options before a byte goes out. A file its machine's
kind cannot take as text (a binary) is refused here in the kind's own words, the words of
its command line (``cellctl dnc send``).

The traffic pane marks the first bytes of the operator's own command (``>>*``): a function
that sends a program, its bytes sent between the call and its answer, never those of a
transfer someone else started (``cellctl dnc send``) after a call that sent nothing.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Protocol, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from cellctl.clock import current_clock
from cellctl.errors import CellctlError, UsageError
from cellctl.files import read_file, reason
from cellctl.kinds import registry
from cellctl.kinds.kind import ProgramRole
from cellctl.service.client import CellClient
from cellctl.service.functions import describe
from cellctl.ui.console.dialogs import Dialog, ParamsDialog, within
from cellctl.ui.console.entry import Action, Entry
from cellctl.ui.console.session import ConsoleMachine
from cellctl.ui.console.traffic import Commands, command_ended

T = TypeVar("T")

#: The API method that lists each machine's functions (a server without it serves none).
SERVED_METHOD = "machines.functions"
#: What the console can ask an operator for (a function asking anything else is unavailable).
ASKABLE = ("program",)
#: Seconds a served call may take when its server gives no deadline of its own.
DEFAULT_TIMEOUT = 30.0
#: Log or detail lines of a result shown under its message.
DETAIL_LINES = 5


class ServedFunction(BaseModel):
    """One function a server offers on a machine (one element of ``machines.functions``)."""

    model_config = ConfigDict(frozen=True, extra="ignore", defer_build=True)
    key: str = Field(min_length=1, max_length=1, pattern=r"^[0-9a-z]$")
    label: str = Field(min_length=1, max_length=40)
    method: str = Field(min_length=1, max_length=100)
    params: dict[str, Any] = Field(default_factory=dict)
    asks: tuple[str, ...] = ()
    confirm: str = Field(default="", max_length=300)
    doc: str = Field(default="", max_length=300)
    timeout_s: float = Field(default=DEFAULT_TIMEOUT, gt=0)


async def served_functions(client: CellClient) -> dict[str, list[ServedFunction]]:
    """Each machine's functions as its server declares them; ``{}`` when it declares none."""
    info = await client.call("server.info")
    if SERVED_METHOD not in (info or {}).get("methods", {}):
        return {}
    return parse_served(await client.call(SERVED_METHOD))


def parse_served(raw: Any) -> dict[str, list[ServedFunction]]:
    """``machines.functions``' answer, checked: ``{machine: [ServedFunction, ...]}``; a
    CellctlError saying what is wrong with it otherwise (a server's answer is not trusted)."""
    if not isinstance(raw, dict):
        raise CellctlError(f"the server's {SERVED_METHOD} is not a menu: {type(raw).__name__}")
    found: dict[str, list[ServedFunction]] = {}
    for name, functions in raw.items():
        if not isinstance(functions, list):
            raise CellctlError(f"the server's {SERVED_METHOD}: {name}: not a list")
        try:
            found[str(name)] = [ServedFunction.model_validate(f) for f in functions]
        except ValidationError as e:
            raise CellctlError(f"the server's {SERVED_METHOD}: {name}: {describe(e)}") from None
    return found


def shop_file(path_text: str, directory: Path) -> tuple[Path, str]:
    """The file a dialog names (relative to ``directory``, the shop), resolved (``..``
    applied, symlinks followed: what is read is what was checked), and the name as the
    operator gave it; UsageError, before anything is read, when it leads out of the shop
    (an absolute path elsewhere, ``..``, a symlink to a file or folder outside)."""
    given = path_text.strip()
    if not given:
        raise UsageError("give a program file")
    path = directory / Path(given).expanduser()
    if not within(path, directory):
        raise UsageError(
            f"{given}: not in the shop '{directory}' (it leads to '{path.resolve()}'): the "
            "program picker reads only files under the shop; copy the program there"
        )
    return path.resolve(), given


def kind_refusal(kind: str | None, path: Path) -> str | None:
    """Why the kind ``kind`` cannot take program file ``path`` as a program, as its own check
    words it (:class:`~cellctl.kinds.kind.ProgramLanguage` ``check``); None when it says
    nothing, or when the kind is not installed here."""
    if kind is None:
        return None
    try:
        found = registry.kind(kind)
        if found.language is None:
            return None
        checked = found.language.check(path, ProgramRole.MILLING, found.checked_options({}))
    except CellctlError:
        return None
    return checked.problems[0] if checked.problems else None


def program_params(raw: dict[str, Any], directory: Path, kind: str | None = None) -> dict[str, Any]:
    """A dialog's program file as the call sends it: its name and text. UsageError if it
    lies outside ``directory`` (before it is read), cannot be read, or is no text: a file
    that is not ASCII is refused in the words of the machine's kind (``kind``), which its
    command line uses too (``cellctl dnc send``)."""
    path, given = shop_file(str(raw.get("program", "")), directory)
    try:
        data = read_file(path)
    except FileNotFoundError:
        raise UsageError(
            f"{given}: no such file in the shop '{directory}' (looked for '{path}'): the "
            "program picker's paths are relative to the shop, not to where the console runs"
        ) from None
    except OSError as e:
        raise UsageError(
            f"{given}: could not open file in the shop '{directory}': {reason(e)}"
        ) from None
    if not data.isascii():
        refusal = kind_refusal(kind, path)
        if refusal is not None:
            raise UsageError(refusal.replace(str(path), given, 1))
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise UsageError(f"{given}: not a text file (byte {e.start + 1} is not UTF-8)") from None
    return {"program": Path(given).name, "text": text}  # named as given (a link by its own)


def progress_words(data: dict[str, Any]) -> str:
    """A pushed progress in words: ``sending 2345/5600 chars, 960 chars/s, 3 s left``."""
    done, total = data.get("chars_sent"), data.get("chars_total")
    words = [str(data.get("phase", ""))]
    if isinstance(done, int) and isinstance(total, int) and total:
        words.append(f"{done}/{total} chars")
    figures = []
    rate = data.get("chars_per_s")
    if isinstance(rate, int | float) and rate > 0:
        figures.append(f"{rate:.0f} chars/s")
    left = data.get("eta_s")
    if isinstance(left, int | float) and math.isfinite(left) and left > 0:
        figures.append(f"{left:.0f} s left")
    stall = data.get("stall_s")
    if isinstance(stall, int | float) and stall > 0:
        figures.append(f"stalled {stall:.1f} s")
    return " ".join(w for w in words if w) + (", " + ", ".join(figures) if figures else "")


class ServedHost(Protocol):
    """What the served menus need of the console app."""

    @property
    def directory(self) -> Path: ...

    @property
    def client(self) -> CellClient | None: ...

    @property
    def commands(self) -> Commands: ...

    def action_up(self) -> None: ...

    def say(self, lines: list[str], style: str = "") -> None: ...

    def show_progress(self, done: float | None, total: float | None) -> None: ...

    async def ask(self, dialog: Dialog[T]) -> T | None: ...

    async def confirm(self, question: str) -> bool: ...


class ServedMenu:
    """A machine's menu from its server's functions, on a console app (:class:`ServedHost`)."""

    def __init__(self, app: ServedHost) -> None:
        self.app = app

    def entries(self, machine: ConsoleMachine, functions: list[ServedFunction]) -> list[Entry]:
        """The functions by their keys, then EXIT on the next number (as the source's menus)."""
        entries = []
        for fn in functions:
            unknown = [a for a in fn.asks if a not in ASKABLE]
            if unknown:
                entries.append(Entry(fn.key, fn.label, None, f"asks for {', '.join(unknown)}"))
            else:
                entries.append(Entry(fn.key, fn.label, self._action(machine, fn)))
        numbers = [int(fn.key) for fn in functions if fn.key.isdigit()]
        entries.append(Entry(str(max(numbers, default=0) + 1), "EXIT", self._back))
        return entries

    async def _back(self) -> None:
        self.app.action_up()

    def _action(self, machine: ConsoleMachine, fn: ServedFunction) -> Action:
        async def action() -> None:
            await self.run(machine, fn)

        return action

    async def run(self, machine: ConsoleMachine, fn: ServedFunction) -> None:
        """Ask for what ``fn`` asks, confirm if it says so, call it and show its outcome."""
        app = self.app
        assert app.client is not None
        title = f"{machine.title} ({machine.name}): {fn.label}"
        params = dict(fn.params)
        if "program" in fn.asks:
            dialog = ParamsDialog(
                title,
                ["program"],
                lambda raw: program_params(raw, app.directory, machine.kind),
                directory=app.directory,
                suffixes=machine.suffixes,
                confined=True,
            )
            answer = await app.ask(dialog)
            if answer is None:
                app.say([f"{machine.name}: {fn.label} cancelled"])
                return
            params.update(answer)
        if fn.confirm and not await app.confirm(f"{machine.name}: {fn.confirm}"):
            app.say([f"{machine.name}: {fn.label} not done"])
            return
        app.say([f"{machine.name}: {fn.label} ..."])
        # The bytes of a function that sends a program are the operator's own (the traffic
        # pane's >>*), looked for from now (traffic rows' wall time) until its answer; a
        # function that sends nothing of its own (LOG, RECEIVE PUNCH) marks nothing.
        sends = "program" in fn.asks
        since = current_clock().now()
        if sends:
            app.commands[machine.name] = since

        def progress(data: dict[str, Any]) -> None:
            done, total = data.get("chars_sent"), data.get("chars_total")
            if isinstance(done, int) and isinstance(total, int) and total:
                app.show_progress(done, total)
            app.say([f"{machine.name}: {fn.label} {progress_words(data)}"])

        try:
            result = await app.client.call(
                fn.method, {**params, "machine": machine.name}, progress, timeout=fn.timeout_s
            )
        except CellctlError as e:
            app.say([f"{machine.name}: {fn.label}: {e}"], "red")
            return
        finally:
            app.show_progress(None, None)
            if sends:  # only what went out before its answer was the operator's
                command_ended(app.commands, machine.name, since, current_clock().now())
        app.say(result_lines(machine.name, fn.label, result), "green")


def result_lines(name: str, label: str, result: Any) -> list[str]:
    """A served function's outcome: its message, then its last detail lines."""
    if not isinstance(result, dict):
        return [f"{name}: {label}: {result}"]
    lines = [f"{name}: {label}: {result.get('message', 'done')}"]
    details = result.get("lines")
    if isinstance(details, list):
        lines += [str(x) for x in details[-DETAIL_LINES:]]
    return lines


__all__ = [
    "SERVED_METHOD",
    "ServedFunction",
    "ServedMenu",
    "parse_served",
    "program_params",
    "progress_words",
    "result_lines",
    "served_functions",
]
