"""Refused logins on the control API are audited and said in the run log, as OPC UA's are:
who (a token's name, a revoked token's name, else "unknown token": never the token), from
where and what was asked; a flood is one growing entry and one log line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.service.audit import AuditLog
from cellctl.service.logins import LOGIN, WRONG_TOKEN, LoginRefusals, foreign_origin
from cellctl.service.token import add_token, ensure_default, list_tokens, revoke_token
from cellctl.service.trail import CallTrail
from cellctl.testing.rig import cli as rig_cli

UNIX = "the Unix socket cell/api.sock"


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    ensure_default(directory)
    return directory


async def audit(cell: Path) -> list[dict[str, object]]:
    """``cellctl audit --since 1m --json``, the real command (in a thread: its own loop)."""
    result = await rig_cli(cell, "audit", "--since", "1m", "--json")
    assert result.exit_code == 0, result.output
    entries: list[dict[str, object]] = json.loads(result.output)
    return entries


async def test_a_flood_of_wrong_tokens_is_one_growing_entry_and_one_log_line(cell: Path) -> None:
    said: list[str] = []
    trail = CallTrail(cell)
    logins = LoginRefusals(trail, say=said.append)
    secret = "guess-" + "x" * 40
    try:
        for _ in range(5):
            await logins.refused(
                {"authorization": f"Bearer {secret}"},
                peer="127.0.0.1:40112",
                asked="GET /api/status",
            )
    finally:
        trail.close()
    entries = await audit(cell)
    assert len(entries) == 1, entries
    (entry,) = entries
    assert (entry["who"], entry["method"], entry["repeats"]) == ("unknown token", LOGIN, 5)
    assert json.loads(str(entry["params"])) == {
        "from": "127.0.0.1:40112",
        "asked": "GET /api/status",
    }
    assert str(entry["result"]).startswith(WRONG_TOKEN)
    assert said == [
        f"login refused for unknown token from 127.0.0.1:40112 (GET /api/status): {WRONG_TOKEN}"
    ]
    text = (cell / "journal.sqlite3").read_bytes()
    assert secret.encode() not in text and secret not in " ".join(said)


async def test_a_revoked_token_and_a_cross_site_call_are_named(cell: Path) -> None:
    said: list[str] = []
    ann = add_token(cell, "ann", "operator")
    bob = add_token(cell, "bob", "viewer")
    revoke_token(cell, "ann")
    trail = CallTrail(cell)
    logins = LoginRefusals(trail, say=said.append)
    try:
        await logins.refused(
            {"authorization": f"Bearer {ann}"}, peer=UNIX, asked="WebSocket /websocket"
        )
        await logins.refused(
            {"authorization": f"Bearer {bob}", "origin": "http://evil.example"},
            peer="127.0.0.1:5000",
            asked="POST /dashboard/call",
            why=foreign_origin("http://evil.example"),
        )
        await logins.refused({}, peer=UNIX, asked="GET /api/alarms")
    finally:
        trail.close()
    with AuditLog(cell) as log:
        found = [(e.who, e.method, e.result) for e in log.entries()]
    assert found == [
        ("token:ann (revoked)", LOGIN, WRONG_TOKEN),
        (
            "token:bob",
            LOGIN,
            "refused: a page of another origin (http://evil.example) sent it "
            "(a cross-site request)",
        ),
        ("no token", LOGIN, WRONG_TOKEN),
    ]
    assert len(said) == 3 and said[0].startswith(
        f"login refused for token:ann (revoked) from {UNIX}"
    )
    assert ann not in " ".join(said) and bob not in " ".join(said)
    # A revoked token's entry keeps a hash only, private, and lets nobody in.
    kept = cell / "tokens" / ".revoked" / "ann"
    assert ann not in kept.read_text() and kept.stat().st_mode & 0o077 == 0
    assert [e.name for e in list_tokens(cell)] == [
        "bob",
        "default",
    ]


async def test_what_a_peer_sent_is_kept_printable(cell: Path) -> None:
    said: list[str] = []
    trail = CallTrail(cell)
    try:
        await LoginRefusals(trail, say=said.append).refused(
            {"authorization": "Basic x"}, peer=UNIX, asked="GET /api/\x1b[31mred"
        )
    finally:
        trail.close()
    assert said == [f"login refused for no token from {UNIX} (GET /api/?[31mred): {WRONG_TOKEN}"]
