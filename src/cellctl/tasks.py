"""Ending what an object started: its tasks cancelled, and waited for until each has ended.

::

    await cancel_and_wait(self._tasks)      # in a close(): nothing it started runs on
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterable
from typing import Any


async def cancel_and_wait(tasks: Iterable[asyncio.Task[Any]]) -> None:
    """Cancel ``tasks`` and wait until each has ended, whatever it raised (a copy is taken:
    a task may leave its owner's set as it ends)."""
    ending = list(tasks)
    for task in ending:
        task.cancel()
    for task in ending:
        with contextlib.suppress(BaseException):
            await task
