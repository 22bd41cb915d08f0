"""The console's WHAT IF waits for a plan as ``cellctl plan`` does (docs/plan.md): while its
play tells how far it has gone, past the silence allowed, how far shown on the result line;
a plan that goes silent is given up in the command line's words and its play ends; the
operator may stop one that plays (CELL -> 9 again).

The silence allowed is the console's parameter (``plan_silence_s``), set short here, and the
plans are a few seconds long. A plan goes silent as a stuck one does: its play's worker
process is stopped (SIGSTOP). The cell is the emulated one, its controller and API in this
process, the console driven with Textual's Pilot on a real API client (a viewer's token).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
from collections.abc import AsyncIterator
from typing import Any

import pytest

from cellctl.service.client import RemoteCell
from cellctl.testing.rig import CellRig
from cellctl.ui.console.app import ConsoleApp
from tests.conftest import until
from tests.test_console import SIZE, fill, screen_text, wait_text
from tests.test_console_whatif import viewer  # noqa: F401 (the fixture)
from tests.test_interrupts_plan import workers_of

#: The silence allowed a plan heard from, s: many of its progress messages (a few a second),
#: and more than its silent start (a worker process spawned at a low priority) takes on a
#: loaded box: 6 s was not, beside a second plan and a browser on 2 cores.
HEARD_SILENCE_S = 12.0
#: A plan playing for longer than that (about 20 s of CPU alone), telling its progress.
LONG = {"horizon": "6h", "add": "wax-robot-base:8", "poll": "2"}
#: The silence allowed a plan that goes silent, s (given up sooner or later: a short one).
SILENCE_S = 3.0
#: A plan of a second or two: the cell's one play is free.
SHORT = {"shift": "2m", "add": ["wax-robot-base:1"]}
#: A hang guard, not a timing figure.
GUARD_S = 120.0


@contextlib.asynccontextmanager
async def plays_stuck() -> AsyncIterator[list[int]]:
    """Within the block, the plan's worker process (this process's) is stopped as soon as it
    runs: the play goes silent, as a stuck one does. The pids stopped; any left at the end
    is killed."""
    stopped: list[int] = []

    async def stop() -> None:
        while True:
            for pid in workers_of(os.getpid()):
                if pid not in stopped:
                    os.kill(pid, signal.SIGSTOP)
                    stopped.append(pid)
            await asyncio.sleep(0.05)

    stopper = asyncio.create_task(stop())
    try:
        yield stopped
    finally:
        stopper.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await stopper
        for pid in stopped:
            if pid in workers_of(os.getpid()):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)


async def worker_ended() -> None:
    """The plan's worker process gone (the API ended its play)."""
    await until(lambda: not workers_of(os.getpid()), "the plan's worker to end", GUARD_S)


async def play_free(client: Any) -> None:
    """The cell's one play free: a short plan is answered, not refused as "being played
    already" (after :func:`plays_stuck`: its worker plays)."""
    answer = await client.call("plan.run", SHORT, timeout=GUARD_S)
    assert answer["plan"]["plans"]


async def seen(pilot: Any, *texts: str) -> str:
    """:func:`~tests.test_console.wait_text` at a slower pace (each look draws the whole
    screen: CPU the plan's play wants), within the hang guard."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 2 * GUARD_S
    while True:
        shown = screen_text(pilot.app)
        if all(t in shown for t in texts) or loop.time() > deadline:
            return await wait_text(pilot, *texts, timeout=1.0)  # the screen, if not there
        await pilot.pause(0.25)


async def ask_plan(pilot: Any, answers: dict[str, str]) -> None:
    await wait_text(pilot, "attached to cellctl run (pid")
    await pilot.press("c", "9")
    await wait_text(pilot, "WHAT IF", "Horizon:")
    for field, value in answers.items():
        await fill(pilot, f"#{field}", value)
    await pilot.press("enter")


@pytest.mark.timeout(300)  # the plan plays on a busy box: CPU, not waiting
async def test_a_plan_heard_from_is_answered_past_the_silence_allowed(
    viewer: tuple[CellRig, RemoteCell],  # noqa: F811
) -> None:
    rig, client = viewer
    app = ConsoleApp(rig.directory, client, traffic_period=0.1, plan_silence_s=HEARD_SILENCE_S)
    async with app.run_test(size=SIZE) as pilot:
        await ask_plan(pilot, LONG)
        # How far it has gone, in `cellctl plan`'s words, while it plays.
        await seen(pilot, "planning... playing: ", "of 6:00:00 machine time")
        shown = await seen(pilot, "Gantt chart, policy downstream-first")
        assert "plan-add1" in shown
        await pilot.press("enter")
        shown = await wait_text(pilot, "plan (downstream-first):")
        assert "nothing heard" not in shown
    rig.check_running()


@pytest.mark.timeout(300)
async def test_a_silent_plan_is_given_up_in_words_and_its_play_ends(
    viewer: tuple[CellRig, RemoteCell],  # noqa: F811
) -> None:
    rig, client = viewer
    app = ConsoleApp(rig.directory, client, traffic_period=0.1, plan_silence_s=SILENCE_S)
    async with app.run_test(size=SIZE) as pilot:
        async with plays_stuck():
            await ask_plan(pilot, LONG)
            # The command line's words (cellctl.service.client.plan_call's).
            shown = await seen(pilot, f"plan.run: nothing heard of the plan for {SILENCE_S:g} s")
            assert "Gantt chart" not in shown
            # Given up, its session closed: the API ended the play (its worker killed).
            await worker_ended()
        await play_free(client)
        # The console goes on: the menu answers.
        await pilot.press("escape")
        await wait_text(pilot, "MAIN MENU")
    rig.check_running()


@pytest.mark.timeout(300)
async def test_the_operator_stops_a_plan_that_plays(
    viewer: tuple[CellRig, RemoteCell],  # noqa: F811
) -> None:
    rig, client = viewer
    # Silent (its worker stopped), so still playing when the operator asks to stop it, and
    # allowed to be for longer than the test: the operator stops it, not the silence.
    app = ConsoleApp(rig.directory, client, traffic_period=0.1, plan_silence_s=10 * GUARD_S)
    async with app.run_test(size=SIZE) as pilot, plays_stuck():
        await ask_plan(pilot, LONG | {"horizon": "24h"})
        await wait_text(pilot, "planning...")
        await pilot.press("9")  # WHAT IF again, while its plan plays
        await wait_text(pilot, "a plan is playing. Stop it?")
        await pilot.press("y")
        shown = await seen(pilot, "plan stopped")
        assert "nothing heard" not in shown and "Gantt chart" not in shown
        await worker_ended()
    await play_free(client)
    rig.check_running()
