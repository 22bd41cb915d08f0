"""Traffic log: every byte both ways, with timestamps, hex and printable text.

Pass ``trace=TrafficLog("robot.trace")`` (or just a path) to ``open_link`` and read the file
after a failure to see exactly what went over the wire::

    2026-11-21 23:59:01.123456  robot1 >>  52                       |R|
    2026-11-21 23:59:01.125801  robot1 <<  13 11                    |..|

``>>`` is host to machine, ``<<`` machine to host. Several links may share one log; each line
names its link. ``TrafficLog(None, keep=2000)`` writes no file and keeps only the last 2,000
chunks in memory: what a running controller holds for the API's traffic tail.
"""

from __future__ import annotations

import datetime as _dt
import os
import threading
from collections import deque
from pathlib import Path
from typing import IO

from cellctl.errors import UsageError

SENT = ">>"
RECEIVED = "<<"


class TrafficLog:
    """Append-only log of link traffic; safe to share between links and threads."""

    def __init__(
        self,
        target: str | Path | IO[str] | None,
        *,
        bytes_per_line: int = 16,
        keep: int | None = None,
    ) -> None:
        self._stream: IO[str] | None
        if isinstance(target, str | Path):
            try:
                # Private, like the cell's other files: a trace holds the programs sent.
                fd = os.open(target, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
            except OSError as e:
                raise UsageError(f"trace file {target}: cannot write it: {e.strerror}") from None
            self._stream = os.fdopen(fd, "a", encoding="utf-8")
            self._owns = True
        else:
            self._stream = target
            self._owns = False
        self._per_line = bytes_per_line
        self._lock = threading.Lock()
        self.entries: deque[tuple[float, str, str, bytes]] = deque(maxlen=keep)
        """What was logged (the last ``keep`` chunks, or all), as (unix time, link label,
        direction, bytes), for tests and tools."""

    def record(self, label: str, direction: str, data: bytes, when: float) -> None:
        """Log ``data`` that went ``direction`` (SENT or RECEIVED) on link ``label``."""
        if not data:
            return
        if self._stream is None:
            with self._lock:
                self.entries.append((when, label, direction, bytes(data)))
            return
        stamp = _dt.datetime.fromtimestamp(when).strftime("%Y-%m-%d %H:%M:%S.%f")
        with self._lock:
            self.entries.append((when, label, direction, bytes(data)))
            for i in range(0, len(data), self._per_line):
                chunk = data[i : i + self._per_line]
                hexpart = " ".join(f"{b:02X}" for b in chunk)
                text = "".join(chr(b) if 32 <= b < 127 else "." for b in chunk)
                width = self._per_line * 3 - 1
                self._stream.write(f"{stamp}  {label} {direction}  {hexpart:<{width}}  |{text}|\n")
            self._stream.flush()

    def sent(self, label: str | None = None) -> bytes:
        """All bytes the host sent (on one link, or on all)."""
        return b"".join(d for _, lab, dr, d in self.entries if dr == SENT and label in (None, lab))

    def received(self, label: str | None = None) -> bytes:
        """All bytes the host received (on one link, or on all)."""
        return b"".join(
            d for _, lab, dr, d in self.entries if dr == RECEIVED and label in (None, lab)
        )

    def tail(self, label: str | None = None, limit: int = 100) -> list[tuple[float, str, bytes]]:
        """The last ``limit`` chunks (on one link, or on all) as (time, direction, bytes)."""
        with self._lock:
            chosen = [(t, d, b) for t, lab, d, b in self.entries if label in (None, lab)]
        return chosen[-limit:] if limit > 0 else []

    def close(self) -> None:
        """Close the file if the log opened it."""
        if self._owns and self._stream is not None:
            self._stream.close()
