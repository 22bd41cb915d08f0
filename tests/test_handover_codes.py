"""The dashboard's hand-over codes as two tokens' holders meet them: one token minting codes
without end pushes out its own oldest ones only, never a code another token was given, and
a code swaps for its own token once. A standalone server on a copy of the example cell, over
real sockets."""

from __future__ import annotations

import json
from pathlib import Path

from cellctl.service.token import add_token
from cellctl.ui.dashboard.handover import MAX_PENDING, PER_TOKEN
from tests.test_api_bodies import post
from tests.test_api_hardening import cell as cell  # the fixture: a copy of the example cell
from tests.test_api_hardening import serve
from tests.test_api_limits import http

JSON = "Content-Type: application/json"


async def mint(port: int, token: str) -> str:
    """A code for ``token`` (``POST /dashboard/handover/new``)."""
    head = post("/dashboard/handover/new", f"Authorization: Bearer {token}", JSON)
    status, body = await http(port, head.replace(b"\r\n\r\n", b"\r\nConnection: close\r\n\r\n"))
    assert status == 200, body
    code: str = json.loads(body)["code"]
    return code


async def swap(port: int, code: str) -> tuple[int, dict[str, object]]:
    """What ``POST /dashboard/handover`` answers for ``code`` (no token)."""
    data = json.dumps({"code": code}).encode()
    head = post("/dashboard/handover", JSON, f"Content-Length: {len(data)}", "Connection: close")
    status, body = await http(port, head + data)
    return status, json.loads(body)


async def test_one_token_minting_codes_pushes_out_only_its_own(cell: Path) -> None:
    line2 = add_token(cell, "line2", "operator")
    async with serve(cell) as served:
        port, default = served.port, served.server.token
        kept = await mint(port, line2)
        # The default token mints more codes than the whole table holds.
        mine = [await mint(port, default) for _ in range(MAX_PENDING + 4)]
        # line2's code still opens the dashboard, with line2's token, once.
        status, answer = await swap(port, kept)
        assert (status, answer) == (200, {"token": line2}), answer
        status, answer = await swap(port, kept)
        assert status == 401 and "spent, has lapsed or is wrong" in json.dumps(answer), answer
        # Of the default token's own codes, its latest PER_TOKEN are good; an older one is not.
        status, answer = await swap(port, mine[-PER_TOKEN - 1])
        assert status == 401, answer
        for code in mine[-PER_TOKEN:]:
            assert await swap(port, code) == (200, {"token": default})
