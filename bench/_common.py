"""Helpers the benchmarks share: emulators in a child process, the test program, output."""

from __future__ import annotations

import asyncio
import math
import multiprocessing as mp
import os
import signal
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from cellctl.kinds.ibm7545.aml import compile_source
from cellctl.kinds.ibm7545.records import ProgramFile
from cellctl.link import LineSettings


def robot_program(records: int, name: str = "BENCH") -> ProgramFile:
    """A program of exactly ``records`` records (N record, moves and delays, end record)."""
    lines = []
    for i in range(records - 3):
        if i % 4 == 3:
            lines.append("DELAY(0)")
        else:
            lines.append(f"PMOVE(PT({300 + i % 50}, {i % 40 - 20}, 0, 0))")
    lines.append("END")
    program = compile_source("\n".join(lines), name, 1)
    assert len(program.records) == records, len(program.records)
    return program


def _child(target: Callable[..., Any], args: tuple[Any, ...], conn: Any) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    asyncio.run(target(conn, *args))


class ChildEmulators:
    """Run ``target(conn, *args)`` (an async function) in another process.

    The target sends the URLs it serves through ``conn`` and serves until the parent closes.
    """

    def __init__(self, target: Callable[..., Any], *args: Any) -> None:
        ctx = mp.get_context("fork")
        self.parent, child = ctx.Pipe()
        self.proc = ctx.Process(target=_child, args=(target, args, child), daemon=True)
        self.proc.start()

    def receive(self, timeout: float = 120.0) -> Any:
        if not self.parent.poll(timeout):
            raise RuntimeError("emulator process did not start")
        return self.parent.recv()

    def cpu_seconds(self) -> float:
        """CPU time (user + system) the emulator process has used so far."""
        try:
            fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return float("nan")
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def close(self) -> None:
        self.parent.send("stop")
        self.proc.join(10)
        if self.proc.is_alive():
            os.kill(self.proc.pid or 0, signal.SIGKILL)


async def wait_for_stop(conn: Any) -> None:
    """In the child: wait (without blocking the loop) until the parent says stop."""
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(None, conn.recv)


async def within(seconds: float, what: str, work: Awaitable[Any]) -> Any:
    """``await work``, but at most ``seconds``: past them, print where every task of the loop
    waits (before any is cancelled) and stop the bench, naming ``what`` did not end."""
    task = asyncio.ensure_future(work)
    try:
        done, _ = await asyncio.wait({task}, timeout=seconds)
    except asyncio.CancelledError:
        task.cancel()  # stopped from outside (Ctrl-C): the work goes with it
        raise
    if task in done:
        return task.result()
    for other in asyncio.all_tasks():
        print(f"--- {other.get_name()}", file=sys.stderr)
        for line in awaiting(other.get_coro()):
            print(f"    {line}", file=sys.stderr)
    task.cancel()
    raise SystemExit(f"{what} did not end within {seconds:g} s (every task above)")


def awaiting(coro: Any) -> list[str]:
    """Where a suspended coroutine waits, outermost first: each ``file:line function`` down
    the chain of what it awaits (a task's own stack shows only the outermost frame)."""
    lines = []
    while coro is not None:
        frame = getattr(coro, "cr_frame", None) or getattr(coro, "gi_frame", None)
        if frame is None:
            lines.append(repr(coro)[:160])  # a future, or a finished coroutine
            break
        lines.append(f"{frame.f_code.co_filename}:{frame.f_lineno} {frame.f_code.co_name}")
        coro = getattr(coro, "cr_await", None) or getattr(coro, "gi_yieldfrom", None)
    return lines


def line_settings() -> LineSettings:
    return LineSettings.parse("4800,7E2")


def machine_line(**pairs: object) -> str:
    """The last, machine-readable line: ``key=value`` pairs."""
    out = []
    for k, v in pairs.items():
        out.append(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}")
    return " ".join(out)


def percentile(values: list[float], q: float) -> float:
    """The nearest-rank percentile (``q`` in 0..100): the smallest value with at least q % of
    the samples at or below it (rank = ceil(q/100 * n)), so the worst samples are never dropped.

    A failed or missed sample belongs in ``values`` as ``math.inf`` (or as the window length,
    said so by the caller): it stays in the count and can become the percentile.
    """
    if not values:
        return float("nan")
    ordered = sorted(values)
    rank = max(1, math.ceil(q / 100 * len(ordered)))
    return ordered[rank - 1]


def median_run(figures: list[float]) -> tuple[float, float, float]:
    """(median, min, max) of repeated runs' figures: benches print the median, never the best."""
    if not figures:
        nan = float("nan")
        return nan, nan, nan
    ordered = sorted(figures)
    return ordered[(len(ordered) - 1) // 2], ordered[0], ordered[-1]
