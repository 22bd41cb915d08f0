"""A menu line of the console: what the app shows and what a menu of its own (the CELL menu)
hands it. Its own module so that the menus and the app both import it, never each other."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass

Action = Callable[[], Awaitable[None]]


@dataclass(frozen=True)
class Entry:
    """One menu line: its key (a number as in the source, or a letter), label, action."""

    key: str
    label: str
    action: Action | None  # None: shown as unavailable
    note: str = ""

    def prompt(self) -> str:
        text = f"{self.key}. {self.label}"
        return f"{text} ({self.note})" if self.note else text
