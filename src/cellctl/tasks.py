"""Ending what an object started, and CPU-bound work handed to processes::

await cancel_and_wait(self._tasks)      # in a close(): nothing it started runs on
with spawned_pool(3) as pool:           # plans side by side, one process each
    reports = list(pool.map(play_one, policies))
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from concurrent.futures import ProcessPoolExecutor


async def cancel_and_wait(tasks: Iterable[asyncio.Task[Any]]) -> None:
    """Cancel ``tasks`` and wait until each has ended, whatever it raised (a copy is taken:
    a task may leave its owner's set as it ends)."""
    ending = list(tasks)
    for task in ending:
        task.cancel()
    for task in ending:
        with contextlib.suppress(BaseException):
            await task


def spawned_pool(jobs: int) -> ProcessPoolExecutor:
    """Worker processes for ``jobs`` CPU-bound jobs (a plan each): at most one a core,
    spawned (clean of the caller's threads and event loop), never forked."""
    # Imported here: every process imports this module, few start a pool.
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    workers = max(1, min(jobs, os.cpu_count() or 1))
    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
