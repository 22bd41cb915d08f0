"""Ending what an object started, and CPU-bound work handed to processes::

await cancel_and_wait(self._tasks)      # in a close(): nothing it started runs on
with spawned_pool(3) as pool:           # plans side by side, one process each
    reports = list(pool.map(play_one, policies))
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import threading
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing.connection import Connection
    from multiprocessing.context import BaseContext

#: Seconds to wait for a killed worker to be reaped (SIGKILL: it ends at once).
REAP_S = 10.0
#: The exit status of a worker whose parent went away (as if killed by SIGHUP).
ORPHANED_EXIT = 128 + signal.SIGHUP


async def cancel_and_wait(tasks: Iterable[asyncio.Task[Any]]) -> None:
    """Cancel ``tasks`` and wait until each has ended, whatever it raised (a copy is taken:
    a task may leave its owner's set as it ends)."""
    ending = list(tasks)
    for task in ending:
        task.cancel()
    for task in ending:
        with contextlib.suppress(BaseException):
            await task


def lifeline(context: BaseContext) -> tuple[Connection, Connection]:
    """A pipe that ties a spawned child's life to this process's: ``(child_end, own_end)``.
    The child is given ``child_end`` and calls :func:`end_with_parent` on it; this process
    keeps ``own_end`` open (it never writes) for as long as the child may live, and closes
    it once the child is reaped. However this process ends (SIGKILL included), the kernel
    closes ``own_end`` and the child ends too."""
    child_end, own_end = context.Pipe(duplex=False)
    return child_end, own_end


def end_with_parent(child_end: Connection) -> None:
    """In a child given a :func:`lifeline`'s end: end this process (at once, no cleanup:
    its work is for a parent that is gone) as soon as the parent's end is closed. Watched by
    a daemon thread, so work that holds the main thread (a plan) is cut short too."""

    def watch() -> None:
        # Nothing is ever sent: any return is the parent's end closing.
        with contextlib.suppress(EOFError, OSError):
            child_end.recv_bytes()
        os._exit(ORPHANED_EXIT)

    threading.Thread(target=watch, name="cellctl-parent-watch", daemon=True).start()


def _pool_worker_start(child_end: Connection) -> None:
    """A :func:`spawned_pool` worker's start: Ctrl-C (sent to the whole process group) is
    its parent's to act on, and the worker ends with its parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    end_with_parent(child_end)


@contextlib.contextmanager
def spawned_pool(jobs: int) -> Iterator[ProcessPoolExecutor]:
    """Worker processes for ``jobs`` CPU-bound jobs (a plan each): at most one a core,
    spawned (clean of the caller's threads and event loop), never forked.

    Left normally, the block waits for the jobs given. Left by an exception (Ctrl-C, SIGTERM
    made an interrupt, an error), the workers are killed and reaped before it goes on: no
    job runs on for a caller that stopped waiting. A worker ignores Ctrl-C (its parent
    decides) and ends by itself if its parent dies (:func:`end_with_parent`)."""
    # Imported here: every process imports this module, few start a pool.
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    context = multiprocessing.get_context("spawn")
    child_end, own_end = lifeline(context)
    workers = max(1, min(jobs, os.cpu_count() or 1))
    pool = ProcessPoolExecutor(
        workers, mp_context=context, initializer=_pool_worker_start, initargs=(child_end,)
    )
    try:
        try:
            yield pool
            pool.shutdown(wait=True)
        except BaseException:
            _kill_workers(pool)
            raise
    finally:
        own_end.close()
        child_end.close()


def _kill_workers(pool: ProcessPoolExecutor) -> None:
    """Kill ``pool``'s workers, drop its jobs not started, and reap the workers (each
    within :data:`REAP_S`), without waiting for any job."""
    # The pool's own map of its workers: shutdown() forgets it, so it is read first.
    workers = list((pool._processes or {}).values())
    for process in workers:
        process.kill()
    pool.shutdown(wait=False, cancel_futures=True)
    for process in workers:
        process.join(REAP_S)
