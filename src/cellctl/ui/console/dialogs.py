"""The console's dialogs (modal screens): a yes/no question, a pick from a list (kept live
where the list changes), a function's parameters (partition, program file with a picker,
forced init, an input to drive and its value) and a small form.

Each dismisses with its answer (None when cancelled with Escape); the app awaits them with
``push_screen_wait`` from a worker.
"""

from __future__ import annotations

import re
from collections.abc import Awaitable, Callable, Iterable
from pathlib import Path
from typing import Any, ClassVar, Generic, TypeVar

from rich.text import Text
from textual import events, on
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Button, Checkbox, DirectoryTree, Input, Label, OptionList, Static
from textual.widgets.option_list import Option

from cellctl.errors import CellctlError, UsageError

T = TypeVar("T")


class FieldRefused(UsageError):
    """A refusal of one field's answer: ``field`` is its id, the field the dialog selects."""

    def __init__(self, message: str, field: str) -> None:
        super().__init__(message)
        self.field = field


class Dialog(ModalScreen[T | None], Generic[T]):
    """A dialog box in the middle of the screen; Escape cancels."""

    BINDINGS: ClassVar[list[BindingType]] = [Binding("escape", "cancel", "Cancel")]
    DEFAULT_CSS = """
    Dialog { align: center middle; }
    Dialog > Vertical {
        width: 76; max-width: 100%; height: auto; max-height: 100%;
        border: thick $accent; background: $surface; padding: 0 1;
    }
    Dialog .title { text-style: bold; width: 100%; }
    Dialog .errors { color: $error; height: auto; max-height: 8; }
    Dialog Horizontal { height: auto; }
    Dialog .field-label { width: 22; padding: 0 1 0 0; }
    Dialog Input { width: 1fr; }
    Dialog .buttons { height: auto; align: right middle; margin-top: 1; }
    Dialog Button { margin: 0 0 0 2; }
    """

    def action_cancel(self) -> None:
        self.dismiss(None)

    def refused(self, problems: str, field: str | None = None) -> None:
        """Show why the answers were refused, and select the text of ``field`` (else of the
        field they name, else of the first), so that what the operator types next replaces
        it. A field is named by its id as a word (``fault``, not the one in ``default``)."""
        self.query_one("#errors", Static).update(Text(problems))
        fields = list(self.query(Input))
        words = problems.replace("_", " ")
        named = [f for f in fields if field is not None and f.id == field] or [
            f
            for f in fields
            if (f.id and re.search(rf"\b{re.escape(f.id.replace('_', ' '))}\b", words))
            or (f.value.strip() and f.value.strip() in problems)
        ]
        for chosen in (named or fields)[:1]:
            chosen.focus()
            chosen.select_all()


class ConfirmDialog(Dialog[bool]):
    """A yes/no question: ``y`` / ``n`` (or Enter on a button)."""

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("y", "answer(True)", "Yes"),
        Binding("n", "answer(False)", "No"),
    ]

    def __init__(self, question: str) -> None:
        super().__init__()
        self.question = question

    def compose(self) -> ComposeResult:
        with Vertical():
            yield Static(Text(self.question), classes="title")
            with Horizontal(classes="buttons"):
                yield Button("Yes (y)", id="yes", variant="warning", compact=True)
                yield Button("No (n)", id="no", compact=True)

    def on_mount(self) -> None:
        self.query_one("#no", Button).focus()

    def action_answer(self, value: bool) -> None:
        self.dismiss(value)

    @on(Button.Pressed)
    def _pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "yes")


class PickDialog(Dialog[str]):
    """Pick one row (Enter, or its number); rows are ``(key, label)``."""

    def __init__(self, title: str, rows: Iterable[tuple[str, str]], hint: str = "") -> None:
        super().__init__()
        self.title_text = title
        self.rows = list(rows)
        self.hint = hint or "Enter picks, Escape goes back"

    def compose(self) -> ComposeResult:
        with Vertical():
            yield Static(Text(self.title_text), classes="title")
            yield OptionList(
                *(Option(label, id=key) for key, label in self.rows), id="pick", markup=False
            )
            yield Static(self.hint, classes="hint")

    def on_mount(self) -> None:
        self.query_one(OptionList).focus()

    @on(OptionList.OptionSelected)
    def _picked(self, event: OptionList.OptionSelected) -> None:
        self.dismiss(event.option.id)

    def on_key(self, event: events.Key) -> None:
        """A number key picks the row numbered so (``1. ACKNOWLEDGE``), as in the menus."""
        if event.character is None or not event.character.isdigit():
            return
        for key, label in self.rows:
            if label.startswith(f"{event.character}. "):
                event.stop()
                self.dismiss(key)
                return

    def show_rows(self, rows: Iterable[tuple[str, str]]) -> None:
        """Show ``rows`` instead, the highlight kept on the same key where it still is."""
        rows = list(rows)
        if rows == self.rows:
            return
        options = self.query_one(OptionList)
        index = options.highlighted
        key = self.rows[index][0] if index is not None and index < len(self.rows) else None
        self.rows = rows
        options.clear_options()
        options.add_options(Option(label, id=k) for k, label in rows)
        keys = [k for k, _ in rows]
        options.highlighted = keys.index(key) if key in keys else (0 if rows else None)


class LivePickDialog(PickDialog):
    """A pick from rows that ``fetch()`` gives again every ``period`` seconds while it is
    open (a list that changes under the operator's eyes, e.g. the orders)."""

    def __init__(
        self,
        title: str,
        rows: Iterable[tuple[str, str]],
        fetch: Callable[[], Awaitable[list[tuple[str, str]]]],
        hint: str = "",
        period: float = 0.5,
    ) -> None:
        super().__init__(title, rows, hint)
        self.fetch = fetch
        self.period = period
        self._fetching = False

    def on_mount(self) -> None:
        super().on_mount()
        self.set_interval(self.period, self._refresh_rows)

    async def _refresh_rows(self) -> None:
        if self._fetching:
            return
        self._fetching = True
        try:
            self.show_rows(await self.fetch())
        except CellctlError as e:
            self.query_one(".hint", Static).update(Text(f"not refreshed: {e}"))
        finally:
            self._fetching = False


def within(path: Path, root: Path) -> bool:
    """Whether ``path``, resolved (``..`` applied, every symlink followed), is under
    ``root`` (resolved too): a symlink or ``..`` leading out of it is not."""
    try:
        return path.resolve().is_relative_to(root.resolve())
    except (OSError, RuntimeError):  # a symlink loop, an unreadable link: not within
        return False


class ProgramTree(DirectoryTree):
    """The cell directory, showing only folders and the family's program files; with
    ``confined``, only what lies within it (no symlink leading out is listed or opened)."""

    def __init__(
        self, path: Path, suffixes: tuple[str, ...], *, confined: bool = False, **kwargs: Any
    ) -> None:
        super().__init__(path, **kwargs)
        self.suffixes = suffixes
        self.confine_to = Path(path) if confined else None

    def filter_paths(self, paths: Iterable[Path]) -> Iterable[Path]:
        return [
            p
            for p in paths
            if not p.name.startswith(".")
            and (p.is_dir() or p.suffix.lower() in self.suffixes)
            and p.name not in ("state", "tokens")  # private: locks, the API's tokens
            and (self.confine_to is None or within(p, self.confine_to))
        ]


class ParamsDialog(Dialog[dict[str, Any]]):
    """A machine function's parameters. ``check(raw)`` turns the answers into the call's
    parameters or raises UsageError; its problems are shown here and nothing is sent."""

    DEFAULT_CSS = """
    ParamsDialog ProgramTree { height: 8; }
    """

    def __init__(
        self,
        title: str,
        fields: Iterable[str],
        check: Callable[[dict[str, Any]], dict[str, Any]],
        *,
        directory: Path,
        suffixes: tuple[str, ...] = (),
        program: str = "",
        confined: bool = False,
    ) -> None:
        """``confined``: the picker lists only what lies within ``directory`` (a shop's)."""
        super().__init__()
        self.title_text = title
        self.fields = set(fields)
        self.check = check
        self.directory = directory
        self.suffixes = suffixes
        self.program = program
        self.confined = confined

    def compose(self) -> ComposeResult:
        with Vertical():
            yield Static(Text(self.title_text), classes="title")
            if "partition" in self.fields:
                with Horizontal():
                    yield Label("Partition (1-5):", classes="field-label")
                    yield Input(id="partition", restrict=r"[0-9]*", max_length=3, compact=True)
            if "program" in self.fields:
                with Horizontal():
                    yield Label("Program file:", classes="field-label")
                    yield Input(self.program, id="program", compact=True)
                yield ProgramTree(self.directory, self.suffixes, confined=self.confined, id="tree")
            if "force" in self.fields:
                yield Checkbox("Force (initialize again)", id="force", compact=True)
            if "input" in self.fields:
                with Horizontal():
                    yield Label("Input (1-16):", classes="field-label")
                    yield Input(id="input", restrict=r"[0-9]*", max_length=3, compact=True)
            if "on" in self.fields:
                yield Checkbox("On (off if not ticked)", id="on", compact=True)
            yield Static("", id="errors", classes="errors")
            with Horizontal(classes="buttons"):
                yield Button("OK", id="ok", variant="primary", compact=True)
                yield Button("Cancel", id="cancel", compact=True)

    def on_mount(self) -> None:
        first = self.query(Input).first() if self.query(Input) else None
        if first is not None:
            first.focus()

    @on(DirectoryTree.FileSelected)
    def _file(self, event: DirectoryTree.FileSelected) -> None:
        path = event.path
        try:
            shown = str(path.relative_to(self.directory))
        except ValueError:
            shown = str(path)
        self.query_one("#program", Input).value = shown

    @on(Input.Submitted)
    def _submitted(self) -> None:
        self.submit()

    @on(Button.Pressed, "#ok")
    def _ok(self) -> None:
        self.submit()

    @on(Button.Pressed, "#cancel")
    def _cancel(self) -> None:
        self.dismiss(None)

    def answers(self) -> dict[str, Any]:
        raw: dict[str, Any] = {}
        for field in ("partition", "program", "input"):
            if field in self.fields:
                raw[field] = self.query_one(f"#{field}", Input).value
        for field in ("force", "on"):
            if field in self.fields:
                raw[field] = self.query_one(f"#{field}", Checkbox).value
        return raw

    def submit(self) -> None:
        """Check the answers: dismiss with the parameters, or show every problem."""
        try:
            params = self.check(self.answers())
        except UsageError as e:
            self.refused(str(e))
            return
        self.dismiss(params)


class FormDialog(Dialog[dict[str, Any]]):
    """A few labelled text fields, e.g. an order's part type, quantity and priority."""

    def __init__(
        self,
        title: str,
        fields: list[tuple[str, str, str]],
        check: Callable[[dict[str, str]], dict[str, Any]],
        problems: str = "",
        *,
        field_of: Callable[[str], str | None] | None = None,
    ) -> None:
        """``fields``: (id, label, default); ``check`` refuses bad answers (UsageError, a
        :class:`FieldRefused` naming its field); ``problems``: a refusal to show from the
        start (the answers asked again); ``field_of``: the field a refusal's words name
        (one that came from elsewhere than ``check``, such as the API's), None if none."""
        super().__init__()
        self.title_text = title
        self.form = fields
        self.check = check
        self.problems = problems
        self.field_of = field_of

    def field_named(self, error: UsageError | str) -> str | None:
        """The field a refusal is about (None: the dialog looks for it in its words)."""
        if isinstance(error, FieldRefused):
            return error.field
        return self.field_of(str(error)) if self.field_of is not None else None

    def compose(self) -> ComposeResult:
        with Vertical():
            yield Static(Text(self.title_text), classes="title")
            for key, label, default in self.form:
                with Horizontal():
                    yield Label(label, classes="field-label")
                    yield Input(default, id=key, compact=True)
            yield Static("", id="errors", classes="errors")
            with Horizontal(classes="buttons"):
                yield Button("OK", id="ok", variant="primary", compact=True)
                yield Button("Cancel", id="cancel", compact=True)

    def on_mount(self) -> None:
        self.query(Input).first().focus()
        if self.problems:
            self.refused(self.problems, self.field_named(self.problems))

    @on(Input.Submitted)
    @on(Button.Pressed, "#ok")
    def _ok(self) -> None:
        raw = {key: self.query_one(f"#{key}", Input).value for key, _, _ in self.form}
        try:
            checked = self.check(raw)
        except UsageError as e:
            self.refused(str(e), self.field_named(e))
            return
        self.dismiss(checked)

    @on(Button.Pressed, "#cancel")
    def _cancel(self) -> None:
        self.dismiss(None)
