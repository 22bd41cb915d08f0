"""Work a service hands to a process of its own, away from the cell's event loop::

    answer = await in_process(play_plan, directory, inputs)  # a module-level function

A plan is seconds of CPU. Played in a thread of the controller's process it takes the
interpreter from the cell's event loop for milliseconds at a time: beside a 2-hour plan in a
thread, a loop's lag was 9.6 ms at the 99th percentile and 27 ms at worst; beside the same
plan in a process of its own, 1.0 ms and 2.6 ms (alone: 0.6 ms and 1.7 ms).

The process is spawned (clean of the service's threads and loop), runs at a lower priority
(:data:`NICE`: the cell's controller comes first), ignores Ctrl-C (stopping is the
service's to do) and ends by itself if the service's process dies, even killed
(:func:`cellctl.tasks.lifeline`). Awaiting it cancelled ends it at once (killed, and reaped
before the await ends: what it wrote may be removed then): a plan nobody waits for any more
burns no CPU, and a service that stops waits for none. A :class:`UsageError` raised in it is
raised here in its own words; any other failure as a :class:`CellctlError` that names it.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import os
import signal
import sys
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any, TypeVar

from cellctl.errors import CellctlError, UsageError
from cellctl.tasks import end_with_parent, lifeline

__all__ = ["NICE", "in_process"]

T = TypeVar("T")

#: How much lower the worker's priority is than the service's (``nice``).
NICE = 10
#: Seconds to wait for a worker that was told to end (killed: it ends at once).
REAP_S = 10.0


def _work(
    send: Connection,
    parent: Connection,
    work: Callable[..., Any],
    args: tuple[Any, ...],
    told: bool = False,
) -> None:
    """The worker process: ``work(*args)``, its outcome sent back as (what, value); ended
    at once if the service's process dies (``parent``: a lifeline's end). ``told``: the
    work is given ``progress=``, which sends ("progress", item) ahead of the outcome."""
    with contextlib.suppress(OSError):
        os.nice(NICE)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    end_with_parent(parent)

    def progress(item: Any) -> None:
        send.send(("progress", item))

    try:
        done = work(*args, progress=progress) if told else work(*args)
        reply: tuple[str, Any] = ("done", done)
    except UsageError as e:
        reply = ("refused", str(e))
    except BaseException as e:  # told to the service in words: its object may not travel
        reply = ("failed", f"{type(e).__name__}: {e}")
    send.send(reply)
    send.close()


@contextlib.contextmanager
def _stderr_with_a_descriptor() -> Iterator[None]:
    """While a process starts: multiprocessing hands its helper (the resource tracker)
    ``sys.stderr``'s descriptor, and a stream that stands in for stderr with a descriptor of
    -1 (a Textual app's: the console captures what is printed) would fail every start
    ("bad value(s) in fds_to_keep"). The process's own stderr stands in meanwhile."""
    try:
        usable = sys.stderr is None or sys.stderr.fileno() >= 0
    except (AttributeError, OSError, ValueError):  # no descriptor at all: left out, fine
        usable = True
    if usable:
        yield
        return
    saved = sys.stderr
    sys.stderr = sys.__stderr__
    try:
        yield
    finally:
        sys.stderr = saved


def _receive(
    receive: Connection, process: BaseProcess, progress: Callable[[Any], None] | None = None
) -> tuple[str, Any]:
    """The worker's reply, or ("ended", None) if it ended without one (killed, crashed);
    its progress on the way to ``progress`` (in this thread)."""
    try:
        while True:
            what, value = receive.recv()
            if what != "progress":
                return what, value
            if progress is not None:
                progress(value)
    except EOFError:
        return "ended", None
    finally:
        receive.close()
        process.join(REAP_S)


async def in_process(
    work: Callable[..., T], *args: Any, progress: Callable[[Any], None] | None = None
) -> T:
    """``work(*args)`` in a spawned worker process (see module docstring): ``work`` a
    module-level function, its arguments and result picklable. ``progress``: ``work`` is
    called with ``progress=`` a function that hands each (picklable) item it is given to
    this ``progress``, called in a thread of this process (not the event loop's)."""
    context = multiprocessing.get_context("spawn")
    receive, send = context.Pipe(duplex=False)
    child_end, own_end = lifeline(context)
    process = context.Process(
        target=_work,
        args=(send, child_end, work, args, progress is not None),
        name=f"cellctl-{work.__name__}",
        daemon=True,
    )
    try:
        with _stderr_with_a_descriptor():
            process.start()
    except BaseException:
        own_end.close()
        receive.close()
        raise
    finally:
        send.close()  # the worker holds its end: its exit is the reader's end of file
        child_end.close()
    reader = asyncio.ensure_future(asyncio.to_thread(_receive, receive, process, progress))
    try:
        what, value = await asyncio.shield(reader)
    finally:
        if process.is_alive():  # cancelled, or the worker replied and is ending anyway
            process.kill()
        # Ended before this returns, even cancelled: what it wrote may be removed after.
        try:
            await reader
        finally:
            own_end.close()  # the worker is reaped (or killed): its lifeline is done
    if what == "done":
        return value  # type: ignore[no-any-return]
    if what == "refused":
        raise UsageError(value)
    if what == "failed":
        raise CellctlError(f"{work.__name__} failed in its process: {value}")
    raise CellctlError(
        f"{work.__name__}'s process ended without an answer (exit code {process.exitcode})"
    )
