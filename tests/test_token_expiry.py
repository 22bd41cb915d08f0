"""Tokens that expire: ``cellctl token add NAME --role ROLE --expires 8h|2026-12-31T18:00``,
shown by ``token list``, refused by the API past their time as a wrong token is, and named
so by the CLI that holds one. The real CLI in its own process, a real server standalone on a
copy of the example cell over loopback; a token already expired is made by rewriting the
``expires`` of an entry the CLI wrote (no command makes one in the past)."""

from __future__ import annotations

import asyncio
import json
import os
import re
import stat
import subprocess
import time
from datetime import datetime
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from websockets.exceptions import ConnectionClosed, InvalidStatus

from cellctl.cell.owner import acquire_controller_lock
from cellctl.errors import UsageError
from cellctl.mailbox import open_mailbox
from cellctl.service.audit import AuditLog
from cellctl.service.token import (
    TOKEN_ENV,
    add_token,
    ensure_default,
    identify,
    list_tokens,
    parse_expiry,
    still_valid,
)
from tests.conftest import CELLCTL, until
from tests.test_api_hardening import answer, call, serve
from tests.test_api_hardening import cell as cell  # the fixture: a copy of the example cell
from tests.test_api_limits import get, http

#: When the expired tokens expired (local time): a fixed past, so its words are known.
PAST = datetime(2024, 5, 1, 18, 0)
PAST_SAID = "2024-05-01 18:00:00"
WRONG = "w" * 43


def cellctl(cell: Path, *args: str, token: str | None = None) -> tuple[int, str, str]:
    """``cellctl --cell CELL ARGS`` in its own process (with ``token`` in $CELLCTL_TOKEN)."""
    env = {k: v for k, v in os.environ.items() if k != TOKEN_ENV}
    if token is not None:
        env[TOKEN_ENV] = token
    done = subprocess.run(
        [*CELLCTL, "--cell", str(cell), *args], capture_output=True, text=True, env=env, timeout=60
    )
    return done.returncode, done.stdout, done.stderr


async def acellctl(cell: Path, *args: str, token: str | None = None) -> tuple[int, str, str]:
    """The same from a test whose server runs in this event loop."""
    return await asyncio.to_thread(cellctl, cell, *args, token=token)


def add(cell: Path, name: str, role: str, *extra: str) -> str:
    """``cellctl token add``: the secret it printed once."""
    code, out, err = cellctl(cell, "token", "add", name, "--role", role, *extra)
    assert code == 0, out + err
    return out.strip()


def expire(cell: Path, name: str) -> None:
    """Move token ``name``'s expiry (made with ``--expires``) to :data:`PAST`, as if that
    time had come: the file is rewritten in place, its mode kept."""
    path = cell / "tokens" / name
    text = path.read_text()
    assert "expires = " in text, text
    path.write_text(re.sub(r"(?m)^expires = .*$", f"expires = {PAST.timestamp()}", text))


def listed(cell: Path) -> dict[str, dict[str, object]]:
    code, out, err = cellctl(cell, "token", "list", "--json")
    assert code == 0, out + err
    return {e["name"]: e for e in json.loads(out)}


def test_add_takes_a_span_or_a_date_and_list_shows_the_expiry(cell: Path) -> None:
    before = time.time()
    add(cell, "shift", "operator", "--expires", "8h")
    after = time.time()
    add(cell, "visit", "viewer", "--expires", "2099-12-31T18:00")
    add(cell, "ann", "operator")  # no --expires: never expires, as before
    for name in ("shift", "visit", "ann"):
        assert stat.S_IMODE((cell / "tokens" / name).stat().st_mode) == 0o600
    # Without --expires the entry is the one an older cellctl wrote: no expires line.
    assert "expires" not in (cell / "tokens" / "ann").read_text()

    found = listed(cell)
    shift = found["shift"]["expires"]
    assert isinstance(shift, float) and before + 8 * 3600 <= shift <= after + 8 * 3600 + 1
    assert found["visit"]["expires"] == datetime(2099, 12, 31, 18, 0).timestamp()
    assert found["ann"]["expires"] is None
    assert not any(e["expired"] for e in found.values())

    code, out, err = cellctl(cell, "token", "list")
    assert code == 0, err
    rows = {line.split()[1]: line for line in out.splitlines() if line.startswith("│")}
    assert "2099-12-31 18:00:00" in rows["visit"]
    assert "never" in rows["ann"] and "never" not in rows["shift"]
    assert "expired" not in out

    code, out, _ = cellctl(cell, "token", "add", "--help")
    assert code == 0 and "never expires" in " ".join(out.split())


@pytest.mark.parametrize(
    ("value", "said"),
    [
        ("8x", "give a span from now (8h, 30d) or a date and time (2026-12-31T18:00)"),
        ("tomorrow", "give a span from now"),
        ("-8h", "give a span from now"),
        ("2000-01-01T00:00", "is past: give a time to come"),
        ("0s", "is past: give a time to come"),
        ("999999999d", "too far ahead"),
    ],
)
def test_a_bad_or_past_expiry_is_refused_before_anything_is_written(
    cell: Path, value: str, said: str
) -> None:
    code, out, err = cellctl(cell, "token", "add", "bob", "--role", "viewer", "--expires", value)
    assert code == 2, out + err
    assert said in " ".join(err.split()) and "Traceback" not in err, err
    assert out == ""  # no secret printed
    assert not (cell / "tokens" / "bob").exists()


NOW = datetime(2026, 6, 1, 12, 0).timestamp()
SPANS = st.builds(lambda n, u: f"{n}{u}", st.integers(0, 10**10), st.sampled_from("smhdwx"))
DATES = st.datetimes().map(lambda d: d.isoformat(timespec="minutes"))


@given(st.one_of(st.text(max_size=40), SPANS, DATES, DATES.map(lambda d: d + "+14:00")))
def test_any_expiry_text_is_a_time_to_come_or_refused_in_words(text: str) -> None:
    try:
        when = parse_expiry(text, now=NOW)
    except UsageError as e:
        assert str(e).startswith("--expires ")
    else:
        assert when > NOW


def test_a_span_counts_from_now_and_a_date_is_local_time() -> None:
    assert parse_expiry("8h", now=NOW) == NOW + 8 * 3600
    assert parse_expiry(" 30d ", now=NOW) == NOW + 30 * 86400
    assert parse_expiry("2026-12-31T18:00", now=NOW) == datetime(2026, 12, 31, 18).timestamp()
    assert parse_expiry("2026-12-31", now=NOW) == datetime(2026, 12, 31).timestamp()
    assert parse_expiry("2026-12-31T18:00Z", now=NOW) == 1798740000.0


def test_the_default_token_never_expires(cell: Path) -> None:
    ensure_default(cell)  # as `cellctl run` does at its start
    [default] = list_tokens(cell)
    assert default.expires is None
    assert "expires" not in (cell / "tokens" / "default").read_text()
    code, _, err = cellctl(cell, "token", "revoke", "default")
    assert code == 0, err
    code, out, err = cellctl(
        cell, "token", "add", "default", "--role", "engineer", "--expires", "8h"
    )
    assert code == 2 and "default" in err and "never expires" in " ".join(err.split()), err
    assert out == "" and not (cell / "tokens" / "default").exists()


def test_an_expired_token_is_listed_so_and_no_longer_identifies(cell: Path) -> None:
    secret = add(cell, "shift", "operator", "--expires", "8h")
    entry = identify(cell, secret)
    assert entry is not None and still_valid(cell, entry)
    expire(cell, "shift")
    assert stat.S_IMODE((cell / "tokens" / "shift").stat().st_mode) == 0o600
    assert identify(cell, secret) is None
    [stale] = list_tokens(cell)  # still listed (revoke removes it)
    assert stale.expires == PAST.timestamp() and not still_valid(cell, stale)

    found = listed(cell)
    assert found["shift"]["expired"] is True
    assert found["shift"]["expires"] == PAST.timestamp()
    code, out, err = cellctl(cell, "token", "list")
    assert code == 0, err
    [row] = [line for line in out.splitlines() if " shift " in line]
    assert PAST_SAID in row and "expired" in row


async def test_the_api_refuses_an_expired_token_as_a_wrong_one(cell: Path) -> None:
    secret = add(cell, "shift", "operator", "--expires", "8h")
    live = add(cell, "ann", "operator", "--expires", "30d")
    expire(cell, "shift")
    async with serve(cell) as served:
        host = f"127.0.0.1:{served.port}"
        status, body = await http(served.port, get("/api/status", host, live))
        assert status == 200 and b"machines" in body
        # HTTP: 401 with the very answer a wrong token gets.
        expired = await http(served.port, get("/api/status", host, secret))
        assert expired[0] == 401
        assert expired == await http(served.port, get("/api/status", host, WRONG))
        # The WebSocket: the handshake refused as for a wrong token.
        refusals = []
        for token in (secret, WRONG):
            with pytest.raises(InvalidStatus) as refused:
                await served.ws(token)
            refusals.append((refused.value.response.status_code, refused.value.response.body))
        assert refusals[0] == refusals[1] and refusals[0][0] in (401, 403)
        ws = await served.ws(live)
        try:
            await ws.send(call(1, "cell.status"))
            assert "result" in await answer(ws, 1)
        finally:
            await ws.close()
    # The refused logins are on record by the expired token's name, never its secret.
    with AuditLog(cell) as log:
        who = {e.who for e in log.entries() if e.method == "api.login"}
    assert "token:shift (expired)" in who and "unknown token" in who, who


async def test_a_session_opened_before_the_expiry_is_refused_after_it(cell: Path) -> None:
    """The one test that waits for a token's time: a session its token opened goes on only
    until then (the server looks at the entry at each call)."""
    async with serve(cell) as served:
        # A margin for the handshake on a loaded machine; the wait after it has a deadline.
        secret = add_token(cell, "brief", "viewer", expires=time.time() + 3)
        ws = await served.ws(secret)
        rid = 0

        async def refused() -> bool:
            nonlocal rid
            rid += 1
            try:
                await ws.send(call(rid, "cell.status"))
                got = await answer(ws, rid)
            except ConnectionClosed:
                return True
            if "error" not in got:
                return False
            assert got["error"]["message"] == "the token 'brief' expired", got
            return True

        try:
            await until(refused, "the expired token's session refused", timeout=60)
        finally:
            await ws.close()


async def test_the_cli_says_its_token_expired_when_and_what_to_do(cell: Path) -> None:
    secret = add(cell, "shift", "operator", "--expires", "8h")
    engineer = add(cell, "eng", "engineer", "--expires", "8h")
    expire(cell, "shift")
    expire(cell, "eng")
    open_mailbox(cell).close()  # without a controller, `orders` then serves the call itself
    async with serve(cell) as served:
        with (cell / "cell.toml").open("a") as toml:  # the dashboard's address: this server
            toml.write(f'\n[api]\nlisten = "127.0.0.1:{served.port}"\n')
        # A controller runs (its lock held, its API on api.sock): the CLI goes through it
        # and says why before it sends the token; the dashboard's URL is not made with it.
        with acquire_controller_lock(cell):
            for args in (("orders",), ("dashboard", "--print")):
                code, out, err = await acellctl(cell, *args, token=secret)
                said = " ".join(err.split())
                assert code == 2 and out == "", err
                assert f"the token 'shift' expired on {PAST_SAID}" in said, said
                assert "cellctl token add NAME --role operator --expires" in said, said
                assert secret not in err and "Traceback" not in err
        # Changing the tokens with an expired engineer's token: refused in the same words,
        # before anything is written.
        code, out, err = await acellctl(
            cell, "token", "add", "eve", "--role", "viewer", token=engineer
        )
        assert code == 2 and f"the token 'eng' expired on {PAST_SAID}" in " ".join(err.split())
        assert not (cell / "tokens" / "eve").exists()
        # Without a controller the CLI serves the call itself: refused there too, in the
        # same words.
        code, out, err = await acellctl(cell, "orders", token=secret)
        said = " ".join(err.split())
        assert code == 2 and f"the token 'shift' expired on {PAST_SAID}" in said, err
        assert secret not in err
        # Nothing the expired token asked reached the server as an act.
        status, _ = await http(served.port, get("/api/status", f"127.0.0.1:{served.port}", secret))
        assert status == 401
