"""Traffic log: every byte both ways, with timestamps, hex and printable text.

Pass ``trace=TrafficLog("robot.trace")`` (or just a path) to ``open_link`` and read the file
after a failure to see exactly what went over the wire::

    2026-11-21 23:59:01.123456  robot1 >>  52                       |R|
    2026-11-21 23:59:01.125801  robot1 <<  13 11                    |..|

``>>`` is host to machine, ``<<`` machine to host. Several links may share one log; each line
names its link.
"""

from __future__ import annotations

import datetime as _dt
import threading
from pathlib import Path
from typing import IO

SENT = ">>"
RECEIVED = "<<"


class TrafficLog:
    """Append-only log of link traffic; safe to share between links and threads."""

    def __init__(self, target: str | Path | IO[str], *, bytes_per_line: int = 16) -> None:
        if isinstance(target, str | Path):
            self._stream: IO[str] = open(target, "a", encoding="utf-8")  # noqa: SIM115
            self._owns = True
        else:
            self._stream = target
            self._owns = False
        self._per_line = bytes_per_line
        self._lock = threading.Lock()
        self.entries: list[tuple[float, str, str, bytes]] = []
        """Everything logged, as (unix time, link label, direction, bytes), for tests and tools."""

    def record(self, label: str, direction: str, data: bytes, when: float) -> None:
        """Log ``data`` that went ``direction`` (SENT or RECEIVED) on link ``label``."""
        if not data:
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

    def close(self) -> None:
        """Close the file if the log opened it."""
        if self._owns:
            self._stream.close()
