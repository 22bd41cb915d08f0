"""Hand-over codes: the dashboard's token into a browser without its command line.

``cellctl dashboard`` opens the page at ``#code=CODE``, not ``#token=...``: a browser started
for it keeps its URL in its command line for as long as it runs, where every user of the host
reads it (``ps``). The code is minted with the token (``POST /dashboard/handover/new``, the
token in the ``Authorization`` header), is good once and for :data:`HANDOVER_S`, and the page
swaps it for the token (``POST /dashboard/handover`` ``{"code": ...}``), which it keeps in its
sessionStorage as it keeps one given in the fragment::

    codes = Handovers()
    code = codes.new(token)      # the CLI's, through the route
    codes.take(code)             # the token, once; None if spent, expired or wrong
"""

from __future__ import annotations

import secrets
from typing import Final

from cellctl.clock import current_clock

#: How long a hand-over code is good, s (the browser opens the page at once).
HANDOVER_S: Final = 60.0
#: Codes kept at most (the oldest goes first): a caller minting many fills nothing.
MAX_PENDING: Final = 16


class Handovers:
    """Codes not taken yet, each with its token and when it lapses (see module docstring)."""

    def __init__(self) -> None:
        self._codes: dict[str, tuple[str, float]] = {}

    def new(self, token: str) -> str:
        """A fresh code for ``token``."""
        now = current_clock().monotonic()
        self._codes = {c: kept for c, kept in self._codes.items() if kept[1] > now}
        while len(self._codes) >= MAX_PENDING:
            del self._codes[min(self._codes, key=lambda c: self._codes[c][1])]
        code = secrets.token_urlsafe(24)
        self._codes[code] = (token, now + HANDOVER_S)
        return code

    def take(self, code: str) -> str | None:
        """The token of ``code``, once; None if it was taken, has lapsed, or is none."""
        kept = self._codes.pop(code, None)
        if kept is None or kept[1] <= current_clock().monotonic():
            return None
        return kept[0]
