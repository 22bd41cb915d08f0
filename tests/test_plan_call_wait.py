"""`cellctl plan` on the running cell waits for ``plan.run`` while its play goes on: a plan
of days on a busy cell takes longer than the API's deadline for one call (600 s) and is
still answered; one that goes silent is given up, and its call cancelled (the cell's play
ends with it). Played on virtual time: the cell here is a stand-in for the API client,
with the client's deadline (``timeout``, else the API's own for ``plan.*``)."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from cellctl.clock import current_clock, run_virtual
from cellctl.errors import LinkTimeout
from cellctl.service.client import PLAN_SILENCE_S, call_timeout, plan_call

WEEK_S = 6 * 86400.0


class PlayingCell:
    """A cell whose ``plan.run`` tells its progress every ``every`` s (None: never) and
    answers after ``takes`` s (None: never), within the call's deadline as the API client
    keeps it."""

    def __init__(self, takes: float | None, every: float | None) -> None:
        self.takes, self.every = takes, every
        self.cancelled = False
        self.told = 0

    async def call(
        self,
        method: str,
        params: dict[str, Any],
        progress: Any = None,
        *,
        timeout: float | None = None,
    ) -> Any:
        clock = current_clock()
        limit = timeout if timeout is not None else call_timeout(method)
        start = clock.monotonic()
        try:
            async with clock.timeout(limit):
                while self.takes is None or clock.monotonic() - start < self.takes:
                    await clock.sleep(self.every or 3600.0)
                    if self.every is not None and progress is not None:
                        self.told += 1
                        progress({"policy": "default", "played_s": 0.0, "span_s": WEEK_S})
        except TimeoutError:
            raise LinkTimeout(
                f"{method}: no answer from the control API within {limit:g} s"
            ) from None
        except asyncio.CancelledError:
            self.cancelled = True
            raise
        return {"plan": "answered"}


def test_a_long_plan_heard_from_is_answered_past_the_api_deadline() -> None:
    cell = PlayingCell(takes=1500.0, every=1.0)
    shown: list[dict[str, Any]] = []

    async def main() -> tuple[Any, float]:
        clock = current_clock()
        start = clock.monotonic()
        answer = await plan_call(cell, {"shift": "6d"}, WEEK_S, shown.append)
        return answer, clock.monotonic() - start

    answer, took = run_virtual(main())
    assert answer == {"plan": "answered"}
    assert took >= 1500.0 > call_timeout("plan.run")
    assert len(shown) == cell.told > 0  # the progress still reaches the line


def test_a_silent_plan_is_given_up_and_its_call_cancelled() -> None:
    cell = PlayingCell(takes=None, every=None)

    async def main() -> None:
        await plan_call(cell, {"shift": "6d"}, WEEK_S)

    with pytest.raises(LinkTimeout, match=f"nothing heard of the plan for {PLAN_SILENCE_S:g} s"):
        run_virtual(main())
    assert cell.cancelled


def test_a_plan_that_goes_silent_midway_is_given_up() -> None:
    cell = PlayingCell(takes=None, every=1.0)

    async def main() -> None:
        async def stops_telling() -> None:
            await current_clock().sleep(900.0)
            cell.every = None

        stopper = asyncio.create_task(stops_telling())
        try:
            await plan_call(cell, {"shift": "6d"}, WEEK_S)
        finally:
            stopper.cancel()

    with pytest.raises(LinkTimeout, match="nothing heard"):
        run_virtual(main())
    assert cell.cancelled


def test_a_plan_slower_than_its_span_is_given_up() -> None:
    cell = PlayingCell(takes=None, every=1.0)

    async def main() -> None:
        await plan_call(cell, {"shift": "20m"}, 1200.0)

    # Heard from all along, but a plan of 20 minutes still playing after the longer of its
    # span and the silence allowed is no plan: the call's own deadline ends it.
    with pytest.raises(LinkTimeout, match="within 1200 s"):
        run_virtual(main())
