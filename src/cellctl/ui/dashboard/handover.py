"""Hand-over codes: the dashboard's token into a browser without its command line.

``cellctl dashboard`` opens the page at ``#code=CODE``, not ``#token=...``: a browser started
for it keeps its URL in its command line for as long as it runs, where every user of the host
reads it (``ps``). The code is minted with the token (``POST /dashboard/handover/new``, the
token in the ``Authorization`` header), is good once and for :data:`HANDOVER_S`, and the page
swaps it for the token (``POST /dashboard/handover`` ``{"code": ...}``), which it keeps in its
sessionStorage as it keeps one given in the fragment::

    codes = Handovers()
    code = codes.new(token, "default")   # the CLI's, through the route (the token's name)
    codes.take(code)             # the token, once; None if spent, expired or wrong
"""

from __future__ import annotations

import secrets
from typing import Final

from cellctl.clock import current_clock

#: How long a hand-over code is good, s (the browser opens the page at once).
HANDOVER_S: Final = 60.0
#: Codes kept at most (the oldest of the token holding the most goes first).
MAX_PENDING: Final = 16
#: Codes one token may have pending (its own oldest goes first): a token minting many
#: pushes out its own codes only, never another token's.
PER_TOKEN: Final = 4


class Handovers:
    """Codes not taken yet, each with its token, the token's name and when it lapses (see
    module docstring)."""

    def __init__(self) -> None:
        self._codes: dict[str, tuple[str, str, float]] = {}

    def new(self, token: str, name: str) -> str:
        """A fresh code for ``token``, whose name (``default``, ``line2``) it counts under."""
        now = current_clock().monotonic()
        codes = {c: kept for c, kept in self._codes.items() if kept[2] > now}
        mine = [c for c, kept in codes.items() if kept[1] == name]
        while len(mine) >= PER_TOKEN:
            del codes[mine.pop(0)]  # insertion order: its oldest first
        if len(codes) >= MAX_PENDING:
            held: dict[str, list[str]] = {}
            for c, kept in codes.items():
                held.setdefault(kept[1], []).append(c)
            del codes[max(held.values(), key=len)[0]]
        code = secrets.token_urlsafe(24)
        codes[code] = (token, name, now + HANDOVER_S)
        self._codes = codes
        return code

    def take(self, code: str) -> str | None:
        """The token of ``code``, once; None if it was taken, has lapsed, or is none."""
        kept = self._codes.pop(code, None)
        if kept is None or kept[2] <= current_clock().monotonic():
            return None
        return kept[0]
