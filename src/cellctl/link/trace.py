"""Traffic log: every byte both ways, with timestamps, hex and printable text.

Pass ``trace=TrafficLog("robot.trace")`` (or just a path) to ``open_link`` and read the file
after a failure to see exactly what went over the wire::

    2026-11-21 23:59:01.123456  robot1 >>  52                       |R|
    2026-11-21 23:59:01.125801  robot1 <<  13 11                    |..|

``>>`` is host to machine, ``<<`` machine to host. Several links may share one log; each line
names its link. ``TrafficLog(None, keep=2000)`` writes no file and keeps only the last 2,000
chunks in memory: what a running controller holds for the API's traffic tail.

A trace is appended to, never rewritten: a file that holds something else (a program, a
cell.toml) is refused when the log is opened, before any link is, so ``--trace load1.rec``
cannot add lines to the program being sent. A command that reads input files refuses a trace
that is one of them by name as well (:func:`refuse_trace_on_inputs`). A write that fails
(a full disk, ``/dev/full``) stops the trace with one warning: the link and the work on it
carry on, as a trace is only a record of them (``TrafficLog.error`` says why it stopped).
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
import re
import stat
import threading
from collections import deque
from collections.abc import Iterable
from pathlib import Path
from typing import IO

from cellctl.errors import UsageError

SENT = ">>"
RECEIVED = "<<"

log = logging.getLogger(__name__)

#: How every line of a trace begins (its time stamp): what an existing file must start with
#: to be appended to.
_TRACE_START = re.compile(rb"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{6}  ")


def refuse_trace_on_inputs(trace: str | Path | None, inputs: Iterable[str | Path]) -> None:
    """UsageError if the trace file ``trace`` is one of ``inputs`` (the files a command
    reads: its programs), however each is written (a symlink, ``./``, ``../dir/``).

    Call it before the trace is opened: appending the trace to a program being sent would
    change the program. Inputs and a trace that do not exist yet are not the same file.
    """
    if trace is None:
        return
    try:
        there = os.stat(trace)
    except OSError:
        return  # not there yet: no input is it
    for name in inputs:
        try:
            if os.path.samestat(there, os.stat(name)):
                raise UsageError(
                    f"trace file {trace} is {name}, which this command reads: "
                    "name another file for the trace"
                )
        except OSError:
            continue


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
                fd = os.open(target, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o600)
            except OSError as e:
                raise UsageError(f"trace file {target}: cannot write it: {e.strerror}") from None
            try:
                _refuse_foreign(fd, target)
            except BaseException:
                os.close(fd)
                raise
            self._stream = os.fdopen(fd, "a", encoding="utf-8")
            self._owns = True
            self.name = str(target)
        else:
            self._stream = target
            self._owns = False
            self.name = str(getattr(target, "name", "the trace")) if target is not None else ""
        self.error: str | None = None
        """Why the trace file stopped (a write failed), None while it is written."""
        self._per_line = bytes_per_line
        self._lock = threading.Lock()
        self.entries: deque[tuple[float, str, str, bytes]] = deque(maxlen=keep)
        """What was logged (the last ``keep`` chunks, or all), as (unix time, link label,
        direction, bytes), for tests and tools."""

    def record(self, label: str, direction: str, data: bytes, when: float) -> None:
        """Log ``data`` that went ``direction`` (SENT or RECEIVED) on link ``label``."""
        if not data:
            return
        if self._stream is None or self.error is not None:
            with self._lock:
                self.entries.append((when, label, direction, bytes(data)))
            return
        stamp = _dt.datetime.fromtimestamp(when).strftime("%Y-%m-%d %H:%M:%S.%f")
        with self._lock:
            self.entries.append((when, label, direction, bytes(data)))
            if self.error is not None:
                return  # stopped by another thread meanwhile
            try:
                for i in range(0, len(data), self._per_line):
                    chunk = data[i : i + self._per_line]
                    hexpart = " ".join(f"{b:02X}" for b in chunk)
                    text = "".join(chr(b) if 32 <= b < 127 else "." for b in chunk)
                    width = self._per_line * 3 - 1
                    line = f"{stamp}  {label} {direction}  {hexpart:<{width}}  |{text}|\n"
                    self._stream.write(line)
                self._stream.flush()
            except (OSError, ValueError) as e:  # ValueError: a stream closed under us
                self._stop(e)

    def _stop(self, e: Exception) -> None:
        """Stop writing the file after a failed write, and say so once."""
        why = getattr(e, "strerror", None) or str(e)
        self.error = f"trace file {self.name}: cannot write it ({why}): the trace stops here"
        log.warning("%s; the link carries on", self.error)

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
            try:
                # A write that failed leaves its text buffered: closing tries it again, and
                # fails again, yet closes the file all the same (io's close always does).
                self._stream.close()
            except OSError as e:
                if self.error is None:
                    self._stop(e)


def _refuse_foreign(fd: int, target: str | Path) -> None:
    """UsageError if the file open as ``fd`` holds something other than a trace: a trace
    is appended to, and lines added to a program or a configuration would change it."""
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode) or st.st_size == 0:
        return  # a new or empty file, a terminal, /dev/null, a pipe
    try:
        reader = os.open(target, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return  # a file we may write but not read: nothing to judge it by
    try:
        if not os.path.samestat(st, os.fstat(reader)):
            return  # replaced since our open: ours is the one written
        head = os.pread(reader, 64, 0)
    finally:
        os.close(reader)
    if not _TRACE_START.match(head):
        raise UsageError(
            f"trace file {target} holds something other than a cellctl trace (a program?): "
            "a trace is only ever appended to its own file: name a new file for it"
        )


__all__ = ["RECEIVED", "SENT", "TrafficLog", "refuse_trace_on_inputs"]
