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
from collections.abc import Callable, Iterable, Iterator
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


#: A :func:`spawned_pool` worker's way to tell its parent how far its job has gone (None:
#: not asked for, or not a pool's worker).
_progress_queue: Any = None
#: Seconds between the parent's looks for a worker's progress (and to end its reader).
PROGRESS_LOOK_S = 0.2


def _pool_worker_start(child_end: Connection, progress: Any = None) -> None:
    """A :func:`spawned_pool` worker's start: Ctrl-C (sent to the whole process group) is
    its parent's to act on, and the worker ends with its parent."""
    global _progress_queue
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    end_with_parent(child_end)
    _progress_queue = progress


def report_progress(item: Any) -> None:
    """In a :func:`spawned_pool` worker: hand ``item`` (picklable) to the pool's
    ``progress`` in the parent; nothing if it was given none (or outside a pool)."""
    if _progress_queue is not None:
        _progress_queue.put(item)


def _read_progress(queue: Any, progress: Callable[[Any], None], done: threading.Event) -> None:
    """The parent's reader of its workers' progress: each item to ``progress``, until
    ``done`` (then what is left)."""
    import queue as queues

    while True:
        try:
            item = queue.get(timeout=PROGRESS_LOOK_S)
        except queues.Empty:
            if done.is_set():
                return
            continue
        except (OSError, EOFError, ValueError):  # the queue closed under it
            return
        progress(item)


@contextlib.contextmanager
def spawned_pool(
    jobs: int, *, progress: Callable[[Any], None] | None = None
) -> Iterator[ProcessPoolExecutor]:
    """Worker processes for ``jobs`` CPU-bound jobs (a plan each): at most one a core,
    spawned (clean of the caller's threads and event loop), never forked.

    ``progress``: called, in a thread of this process, with each item a job hands
    :func:`report_progress` (how far a plan has gone).

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
    queue = context.Queue() if progress is not None else None
    pool = ProcessPoolExecutor(
        workers, mp_context=context, initializer=_pool_worker_start, initargs=(child_end, queue)
    )
    done = threading.Event()
    reader = None
    if queue is not None and progress is not None:
        reader = threading.Thread(target=_read_progress, args=(queue, progress, done), daemon=True)
        reader.start()
    try:
        try:
            yield pool
            pool.shutdown(wait=True)
        except BaseException:
            _kill_workers(pool)
            raise
    finally:
        done.set()
        if reader is not None:
            reader.join(REAP_S)
        if queue is not None:
            queue.close()
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
