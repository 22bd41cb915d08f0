"""How far a plan has played, on one line of a terminal, while it plays::

    with progress_line(as_json) as line:        # None unless stderr is a terminal
        result = play_in_temp(inputs, policies, progress=line and line.told(span_s))

A plan of days takes minutes: on a terminal (stderr a tty) a line says how much of its
machine time each policy has played and, from the pace so far, how long the rest takes at
most (a plan ends sooner when every order is done), rewritten in place and cleared before
the plan is printed. In a pipe, or with ``--json``, nothing is written.
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any, TextIO

from cellctl.clock import REAL_CLOCK, Clock
from cellctl.plan.when import span_text

__all__ = ["ProgressLine", "progress_line"]

#: The computer's seconds of play before the line says how long the rest takes: the pace
#: of the first moments (the cell connecting, processes starting) says little.
ESTIMATE_AFTER_S = 3.0


class ProgressLine:
    """One line on ``stream`` (a terminal): each policy's machine time played of the span,
    and how long the rest takes at most at the pace so far (on ``clock``: the computer's
    time). Thread-safe: a pool's progress comes from a thread of its own."""

    def __init__(self, stream: TextIO, clock: Clock = REAL_CLOCK) -> None:
        self.stream = stream
        self.clock = clock
        self._began = clock.monotonic()
        self.span_s = 0.0
        self._played: dict[str, float] = {}
        self._lock = threading.Lock()
        self._shown = False

    def update(self, policy: str, played_s: float, span_s: float | None = None) -> None:
        """``policy`` has played ``played_s`` machine seconds (of ``span_s``, if given)."""
        with self._lock:
            if span_s is not None:
                self.span_s = span_s
            self._played[policy] = played_s
            self.stream.write("\r" + self.text() + "\x1b[K")
            self.stream.flush()
            self._shown = True

    def text(self) -> str:
        """``playing: 2:13:00 of 8:00:00 machine time (28%, up to about 0:00:05 more)``;
        with several policies, each one's share."""
        span = max(self.span_s, 1e-9)
        more = self._more()
        if len(self._played) == 1:
            [played] = self._played.values()
            return (
                f"playing: {span_text(played)} of {span_text(self.span_s)} machine time "
                f"({min(1.0, played / span):.0%}{f', {more}' if more else ''})"
            )
        # Here, not at the top: `cellctl plan --help` loads none of the plan's engine.
        from cellctl.plan.report import policy_name

        each = ", ".join(
            f"{policy_name(p)} {min(1.0, s / span):.0%}" for p, s in self._played.items()
        )
        return f"playing {span_text(self.span_s)} of machine time: {each}" + (
            f" ({more})" if more else ""
        )

    def _more(self) -> str:
        """``up to about 0:09:40 more``: how long the machine time left to play (every
        policy's) takes at the pace played so far; empty until there is a pace to go by."""
        took = self.clock.monotonic() - self._began
        played = sum(self._played.values())
        if took < ESTIMATE_AFTER_S or played <= 0:
            return ""
        left = sum(max(0.0, self.span_s - p) for p in self._played.values()) * took / played
        return "under a minute more" if left < 60 else f"up to about {span_text(left)} more"

    def told(self, span_s: float) -> Callable[[str, float], None]:
        """What a play is told its progress with (``(policy, played_s)``), of ``span_s``."""
        self.span_s = span_s
        return self.update

    def from_api(self, data: dict[str, Any]) -> None:
        """``plan.run``'s progress (``{"policy", "played_s", "span_s"}``)."""
        try:
            self.update(str(data["policy"]), float(data["played_s"]), float(data["span_s"]))
        except (KeyError, TypeError, ValueError):
            return  # not a plan's progress: nothing to show

    def close(self) -> None:
        """Clear the line (the plan's own output follows)."""
        with self._lock:
            if self._shown:
                self.stream.write("\r\x1b[K")
                self.stream.flush()
                self._shown = False


@contextlib.contextmanager
def progress_line(quiet: bool) -> Iterator[ProgressLine | None]:
    """A :class:`ProgressLine` on stderr if it is a terminal and not ``quiet`` (``--json``),
    cleared when the block ends; else None."""
    stream = sys.stderr
    try:
        terminal = stream is not None and stream.isatty()
    except (AttributeError, ValueError):
        terminal = False
    if quiet or not terminal:
        yield None
        return
    line = ProgressLine(stream)
    try:
        yield line
    finally:
        line.close()
