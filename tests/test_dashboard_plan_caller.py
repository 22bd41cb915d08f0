"""A plan asked for over HTTP (``POST /dashboard/call``) ends when its caller goes away, as
one over the websocket does: it holds the cell's one play, and a plan of a month at a fine
poll would otherwise play on for an hour with nobody to read it."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from cellctl.service.token import read_token
from cellctl.testing.rig import CellRig
from tests.conftest import until
from tests.test_dashboard import dashboard_served, http

LONG = {"shift": "744h", "add": ["wax-robot-base:2000"], "poll": 0.5}
SHORT = {"shift": "2m", "add": ["wax-robot-base:1"]}


@pytest.fixture
async def served(tmp_path: Path) -> AsyncIterator[tuple[str, int, str]]:
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        async with dashboard_served(rig) as (_, base):
            yield base, int(base.rsplit(":", 1)[1]), read_token(rig.directory)


async def test_a_plan_whose_caller_left_stops_and_frees_the_play(
    served: tuple[str, int, str],
) -> None:
    base, port, token = served
    body = json.dumps({"method": "plan.run", "params": LONG}).encode()
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(
        b"POST /dashboard/call HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        + f"Authorization: Bearer {token}\r\nContent-Type: application/json\r\n".encode()
        + f"Content-Length: {len(body)}\r\n\r\n".encode()
        + body
    )
    await writer.drain()
    call = {"method": "plan.run", "params": SHORT}

    async def refused_as_playing() -> bool:
        status, answer = await http(base + "/dashboard/call", token=token, body=call)
        return status != 200 and "being played already" in json.dumps(answer)

    await until(refused_as_playing, "the long plan playing (a second one refused)")
    writer.close()  # the caller goes away
    await writer.wait_closed()
    assert not await reader.read()  # nothing was answered to it

    async def planned() -> bool:
        # A plan's play starts a worker process: on a loaded box that alone can take seconds.
        status, answer = await http(base + "/dashboard/call", token=token, body=call, timeout=45)
        return status == 200 and "plan" in answer["result"]

    await until(planned, "a new plan played: the long one ended with its caller", 60)
