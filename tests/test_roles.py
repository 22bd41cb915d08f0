"""Tokens with roles, checked on every surface of the control API, and the audit trail."""

from __future__ import annotations

import asyncio
import contextlib
import getpass
import json
import os
import shutil
import stat
import subprocess
from collections.abc import AsyncIterator
from datetime import datetime
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st
from websockets.exceptions import ConnectionClosed

from cellctl.cell.journal import JOURNAL_FILE, open_journal
from cellctl.cell.owner import acquire_controller_lock
from cellctl.errors import AccessDenied, CellctlError, UsageError
from cellctl.service.audit import AuditLog
from cellctl.service.client import RemoteCell
from cellctl.service.server import ApiServer
from cellctl.service.token import (
    ROLES,
    TOKEN_ENV,
    TOKEN_NAME,
    add_token,
    check_name,
    ensure_default,
    identify,
    list_tokens,
)
from cellctl.testing.rig import CellRig
from cellctl.testing.rig import cli as rig_cli
from cellctl.ui.cli import main as cli_main
from tests.conftest import CELLCTL
from tests.test_dashboard import dashboard_served, http


@pytest.fixture
async def served(tmp_path: Path) -> AsyncIterator[tuple[CellRig, ApiServer, str]]:
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        assert rig.controller is not None
        # An older cell: only api-token, no tokens/ yet.
        (rig.directory / "api-token").unlink(missing_ok=True)
        (rig.directory / "api-token").write_text("old-" + "x" * 40 + "\n")
        assert not (rig.directory / "tokens").exists()
        async with dashboard_served(rig) as (server, base):
            yield rig, server, base


def cli_sync(cell: Path, *args: str) -> tuple[int, str]:
    result = CliRunner().invoke(cli_main, ["--cell", str(cell), *args])
    return result.exit_code, result.output


async def cli(cell: Path, *args: str) -> tuple[int, str]:
    result = await rig_cli(cell, *args)
    return result.exit_code, result.output


async def connect(server: ApiServer, token: str) -> RemoteCell:
    return await RemoteCell.connect(token=token, socket_path=server.socket_path)


async def test_roles_on_websocket_http_and_the_dashboard_and_the_audit_trail(
    served: tuple[CellRig, ApiServer, str],
) -> None:
    rig, server, base = served
    cell = rig.directory
    code, out = await cli(cell, "token", "add", "vera", "--role", "viewer")
    assert code == 0, out
    viewer = out.splitlines()[0].strip()
    code, out = await cli(cell, "token", "add", "otto", "--role", "operator")
    assert code == 0, out
    operator = out.splitlines()[0].strip()
    for name in ("vera", "otto"):
        path = cell / "tokens" / name
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        assert viewer not in path.read_text() and operator not in path.read_text()
    assert stat.S_IMODE((cell / "tokens").stat().st_mode) == 0o700
    # Tokens are changed by an engineer: with a viewer's or an operator's token in
    # $CELLCTL_TOKEN the command is refused (and the refusal is in the audit trail).
    code, out = await cli_as(cell, viewer, "token", "add", "eve", "--role", "engineer")
    assert code == 7 and "vera is a viewer: token.add needs the engineer role" in out, out
    code, out = await cli_as(cell, operator, "token", "revoke", "vera")
    assert code == 7 and "otto is an operator: token.revoke needs the engineer role" in out, out
    code, out = await cli_as(cell, "not-a-token", "token", "revoke", "vera")
    assert code == 7 and "no token of" in out, out
    assert sorted(p.name for p in (cell / "tokens").iterdir()) == ["default", "otto", "vera"]

    # The WebSocket: a viewer reads, and is refused an order with the role it lacks.
    vera = await connect(server, viewer)
    try:
        assert "machines" in await vera.call("cell.status", {})
        with pytest.raises(
            AccessDenied, match=r"vera is a viewer: orders\.submit needs the operator"
        ):
            await vera.call("orders.submit", {"part_type": "wax-robot-base"})
    finally:
        await vera.close()

    # HTTP: a viewer's POST is refused with 403 and the role it lacks; a GET of an
    # operator's read too.
    call = {"method": "orders.submit", "params": {"part_type": "wax-robot-base"}}
    status, body = await http(base + "/dashboard/call", token=viewer, body=call)
    assert status == 403
    assert body["error"]["data"]["role"] == "operator"
    assert "needs the operator role" in body["error"]["message"]
    status, body = await http(base + "/api/status", token=viewer)
    assert status == 200 and "machines" in body

    # An operator orders through the dashboard's call; an audit entry says who and what.
    status, body = await http(base + "/dashboard/call", token=operator, body=call)
    assert status == 200, body
    order_id = body["result"]["order"]["id"]
    status, body = await http(
        base + "/dashboard/call", token=operator, body={"method": "audit.list", "params": {}}
    )
    assert status == 200, body
    entries = body["result"]
    ok = [e for e in entries if e["method"] == "orders.submit" and e["result"] == "ok"]
    assert [e["who"] for e in ok] == ["token:otto"]
    assert "wax-robot-base" in ok[0]["params"]
    refused = [e for e in entries if e["who"] == "token:vera"]
    assert {e["method"] for e in refused} == {"orders.submit", "token.add"}
    assert all(
        "needs the operator role" in e["result"] for e in refused if e["method"] != "token.add"
    )
    assert any("needs the engineer role" in e["result"] for e in refused)
    # The refused token change with what it asked for, as every refused call is kept.
    (asked,) = [e for e in refused if e["method"] == "token.add"]
    assert '"name":"eve"' in asked["params"] and '"role":"engineer"' in asked["params"]
    assert rig.mailbox.get_order(order_id).part_type == "wax-robot-base"
    # A viewer reads the audit trail too (the dashboard's Audit panel).
    status, body = await http(
        base + "/dashboard/call", token=viewer, body={"method": "audit.list", "params": {}}
    )
    assert status == 200 and any(e["who"] == "token:otto" for e in body["result"])

    # The CLI's audit reads the same entries; --who filters.
    code, out = await cli(cell, "audit", "--who", "otto", "--json", "--since", "1h")
    assert code == 0, out
    assert '"token:otto"' in out and "token:vera" not in out

    # A revoked token is refused at once: its open session's next call, and a new request.
    otto = await connect(server, operator)
    try:
        assert await otto.call("orders.list", {}) is not None
        code, out = await cli(cell, "token", "revoke", "otto")
        assert code == 0 and "revoked" in out
        with pytest.raises((AccessDenied, ConnectionClosed)):
            await otto.call("orders.list", {})
    finally:
        await otto.close()
    status, _ = await http(base + "/api/status", token=operator)
    assert status == 401
    code, out = await cli(cell, "token", "list")
    assert code == 0 and "vera" in out and "otto" not in out and viewer not in out


async def test_an_older_cell_with_only_api_token_keeps_it_as_the_engineer_default(
    served: tuple[CellRig, ApiServer, str],
) -> None:
    rig, server, _ = served
    cell = rig.directory
    token = (cell / "api-token").read_text().strip()
    [default] = list_tokens(cell)
    assert (default.name, default.role) == ("default", "engineer")
    assert stat.S_IMODE((cell / "tokens" / "default").stat().st_mode) == 0o600
    assert token not in (cell / "tokens" / "default").read_text()
    # The CLI (which reads api-token) acts as an engineer: a by-hand robot function passes
    # the role check (and is refused only because the robot is in automatic service).
    client = await connect(server, token)
    try:
        with pytest.raises(Exception) as refused:
            await client.call("robot.home", {})
        assert "needs the" not in str(refused.value)
        await client.call("cell.pause", {})
        await client.call("cell.resume", {})
    finally:
        await client.close()
    with AuditLog(cell) as log:
        whos = {(e.who, e.method, e.result) for e in log.entries()}
    assert ("token:default", "cell.pause", "ok") in whos


def test_token_files_and_refusals(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    cell.mkdir()
    shutil.copy(Path(__file__).parent.parent / "examples" / "cell" / "cell.toml", cell)
    secret = add_token(cell, "ann", "operator")
    assert len(secret) >= 32
    entry = identify(cell, secret)
    assert entry is not None and (entry.name, entry.role) == ("ann", "operator")
    assert identify(cell, secret + "x") is None
    with pytest.raises(UsageError, match="exists"):
        add_token(cell, "ann", "viewer")
    with pytest.raises(UsageError, match="role 'root'"):
        add_token(cell, "bob", "root")
    # A link in a token's place is refused, never followed.
    os.symlink(cell / "tokens" / "ann", cell / "tokens" / "evil")
    assert [e.name for e in list_tokens(cell)] == ["ann"]
    code, out = cli_sync(cell, "token", "add", "../x", "--role", "viewer")
    assert code == 2 and "token name '../x'" in out


@given(st.text(max_size=80))
def test_a_token_name_is_taken_only_when_it_is_a_plain_file_name(name: str) -> None:
    try:
        check_name(name)
    except UsageError as e:
        assert "token name" in str(e)
        assert not TOKEN_NAME.fullmatch(name)
    else:
        assert "/" not in name and not name.startswith(".") and 1 <= len(name) <= 64
        assert name.isascii() and name.isprintable()


WRONG = "w" * 43


async def cli_as(cell: Path, token: str, *args: str) -> tuple[int, str]:
    """``cellctl`` acting with ``token`` ($CELLCTL_TOKEN), in a worker thread."""

    def invoke() -> tuple[int, str]:
        result = CliRunner().invoke(cli_main, ["--cell", str(cell), *args], env={TOKEN_ENV: token})
        return result.exit_code, result.output

    return await asyncio.to_thread(invoke)


async def test_each_role_and_a_wrong_token_on_each_surface(
    served: tuple[CellRig, ApiServer, str],
) -> None:
    """viewer, operator, engineer and a wrong token, each on the WebSocket, an HTTP GET,
    the dashboard's POST and the CLI (which the console shares: $CELLCTL_TOKEN, through the
    controller's API): a read, an operator's action and an engineer's by-hand function."""
    rig, server, base = served
    cell = rig.directory
    tokens = {role: add_token(cell, f"t-{role}", role) for role in ROLES}

    # A wrong token: no handshake, 401 on HTTP and on the dashboard's call, and the CLI
    # says so.
    with pytest.raises(AccessDenied, match="refused the token"):
        await connect(server, WRONG)
    assert (await http(base + "/api/status", token=WRONG))[0] == 401
    call = {"method": "alarms.ack", "params": {"id": 999}}
    assert (await http(base + "/dashboard/call", token=WRONG, body=call))[0] == 401
    # The CLI says it in the same words whether it goes through the API (a controller
    # runs: its lock is held, as by `cellctl run`) or runs the call itself.
    said = f"$CELLCTL_TOKEN is no token of {cell} (wrong or revoked)"
    code, out = await cli_as(cell, WRONG, "orders")
    assert code == 7 and said in out, out
    with acquire_controller_lock(cell):
        code, out = await cli_as(cell, WRONG, "orders")
        assert code == 7 and said in out, out
        # Not a token at all (a line break pasted in): the same words, never sent (a header
        # with it is not HTTP: it failed as an API that does not answer, and showed it).
        code, out = await cli_as(cell, "pasted\nsecret-tail", "orders")
        assert code == 7 and said in out and "secret-tail" not in out, out

        for role, token in tokens.items():
            needs = {"viewer": "operator", "operator": "engineer", "engineer": None}[role]
            client = await connect(server, token)
            try:
                assert "machines" in await client.call("cell.status", {})
                if role == "viewer":
                    with pytest.raises(AccessDenied, match=r"cell\.pause needs the operator role"):
                        await client.call("cell.pause", {})
                else:
                    await client.call("cell.pause", {})
                    await client.call("cell.resume", {})
                with pytest.raises(CellctlError) as home:
                    await client.call("robot.home", {})
                if role == "engineer":  # past the role: refused for the automatic service
                    assert "in automatic service" in str(home.value)
                else:
                    assert "robot.home needs the engineer role" in str(home.value)
            finally:
                await client.close()

            status, body = await http(base + "/api/status", token=token)
            assert status == 200 and "machines" in body
            status, body = await http(base + "/dashboard/call", token=token, body=call)
            if role == "viewer":
                assert status == 403 and body["error"]["data"]["role"] == "operator"
            else:  # past the role: there is no alarm 999
                assert status == 400 and "no alarm 999" in body["error"]["message"]

            code, out = await cli_as(cell, token, "orders", "--json")
            assert code == 0, out
            code, out = await cli_as(cell, token, "alarm", "ack", "999")
            assert code != 0
            if needs == "operator":
                assert "alarms.ack needs the operator role" in out
            else:
                assert "no alarm 999" in out
            code, out = await cli_as(cell, token, "robot", "robot", "home")
            assert code != 0
            if needs is None:
                assert "in automatic service" in out
            else:
                assert "robot.home needs the engineer role" in out

    # Every refusal and every action is in the trail under the token's name.
    with AuditLog(cell) as log:
        seen = {(e.who, e.method, "needs the" in e.result) for e in log.entries(limit=10_000)}
    assert ("token:t-viewer", "cell.pause", True) in seen
    assert ("token:t-operator", "cell.pause", False) in seen
    assert ("token:t-operator", "robot.home", True) in seen
    assert ("token:t-engineer", "robot.home", False) in seen
    assert ("token:t-viewer", "alarms.ack", True) in seen


async def test_without_a_controller_the_cli_acts_with_its_tokens_role(tmp_path: Path) -> None:
    """No controller runs: the CLI serves the call in its own process, and with
    $CELLCTL_TOKEN it acts with that token's role (a viewer reads the alarm history, may
    not acknowledge or shelve); a token that is not the cell's is refused."""
    async with CellRig(tmp_path / "cell") as rig:
        cell = rig.directory
        viewer = add_token(cell, "vera", "viewer")
        code, out = await cli_as(cell, viewer, "alarm", "history", "--json")
        assert code == 0 and out.strip().startswith("["), out
        for args in (("alarm", "ack", "1"), ("alarm", "shelve", "1", "--for", "30m")):
            code, out = await cli_as(cell, viewer, *args)
            assert code != 0 and "vera is a viewer" in out and "needs the operator role" in out
        code, out = await cli_as(cell, WRONG, "alarm", "history")
        assert code != 0 and "CELLCTL_TOKEN is no token of" in out
    with AuditLog(cell) as log:
        refused = [(e.who, e.method) for e in log.entries() if "needs the" in e.result]
    assert refused == [("token:vera", "alarms.ack"), ("token:vera", "alarms.shelve")]


def test_token_changes_are_in_the_audit_trail(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    open_journal(cell).close()  # a cell that ran: its journal holds the trail
    shutil.copy(Path(__file__).parent.parent / "examples" / "cell" / "cell.toml", cell)
    assert cli_sync(cell, "token", "add", "ann", "--role", "operator")[0] == 0
    assert cli_sync(cell, "token", "revoke", "ann")[0] == 0
    with contextlib.closing(AuditLog(cell)) as log:
        done = [(e.method, e.params, e.result) for e in log.entries()]
    assert done == [
        ("token.add", '{"name":"ann","role":"operator"}', "ok"),
        ("token.revoke", '{"name":"ann"}', "ok"),
    ]
    code, out = cli_sync(cell, "audit", "--json")
    assert code == 0 and '"token.revoke"' in out and f'"local:{getpass.getuser()}"' in out


def test_a_token_made_to_expire_is_audited_with_the_time_it_expires(tmp_path: Path) -> None:
    """``token add --expires``: the trail keeps the time it came to (with its offset), not a
    span from an unknown moment; the real CLI, in its own process."""
    cell = tmp_path / "cell"
    open_journal(cell).close()
    shutil.copy(Path(__file__).parent.parent / "examples" / "cell" / "cell.toml", cell)
    env = {k: v for k, v in os.environ.items() if k != TOKEN_ENV}
    args = ["token", "add", "shift", "--role", "operator", "--expires", "2099-12-31T18:00"]
    done = subprocess.run(
        [*CELLCTL, "--cell", str(cell), *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert "expires 2099-12-31 18:00:00" in done.stderr
    with contextlib.closing(AuditLog(cell)) as log:
        [(method, params, result)] = [(e.method, e.params, e.result) for e in log.entries()]
    assert (method, result) == ("token.add", "ok")
    asked = json.loads(params)
    assert (asked["name"], asked["role"]) == ("shift", "operator")
    assert datetime.fromisoformat(asked["expires"]) == datetime(2099, 12, 31, 18, 0).astimezone()


def test_revoking_default_says_what_this_computer_acts_with_now(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    cell.mkdir()
    shutil.copy(Path(__file__).parent.parent / "examples" / "cell" / "cell.toml", cell)
    ensure_default(cell)  # as `cellctl run` does at its start
    code, out = cli_sync(cell, "token", "revoke", "default")
    said = " ".join(out.split())
    assert code == 0 and "token default revoked" in said, out
    assert "api-token removed with it: commands here act with $CELLCTL_TOKEN" in said
    assert not (cell / "api-token").exists()
    code, out = cli_sync(cell, "token", "list")
    assert code == 0 and "default" not in out.replace("as `default`", ""), out


def test_a_cell_that_never_ran_keeps_its_trail_from_the_first_action(tmp_path: Path) -> None:
    """An order posted (and one refused) before the first ``cellctl run``, and a token made:
    audited, the journal made for it private; a directory that is no cell gets no journal."""
    cell = tmp_path / "cell"
    shutil.copytree(Path(__file__).parent.parent / "examples" / "cell", cell)
    assert not (cell / JOURNAL_FILE).exists()
    code, out = cli_sync(cell, "submit", "wax-robot-base", "--qty", "2", "--id", "first")
    assert code == 0, out
    code, out = cli_sync(cell, "cancel", "no-such-order")
    assert code != 0, out
    assert cli_sync(cell, "token", "add", "ann", "--role", "operator")[0] == 0
    assert stat.S_IMODE((cell / JOURNAL_FILE).stat().st_mode) == 0o600
    with contextlib.closing(AuditLog(cell)) as log:
        done = [(e.who, e.method, e.result) for e in log.entries()]
    me = f"local:{getpass.getuser()}"
    assert [(who, method) for who, method, _ in done] == [
        (me, "orders.submit"),
        (me, "orders.cancel"),
        (me, "token.add"),
    ]
    assert done[0][2] == "ok" and "no-such-order" in done[1][2] and done[2][2] == "ok"
    # The journal the trail made is the cell's journal: a run and its listings take it.
    code, out = cli_sync(cell, "part", "list")
    assert code == 0, out
    # Not a cell (no cell.toml, a mailbox only): nothing audited, no journal made.
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "mailbox.sqlite3").write_bytes((cell / "mailbox.sqlite3").read_bytes())
    code, out = cli_sync(bare, "cancel", "first")
    assert code == 0, out
    assert not (bare / JOURNAL_FILE).exists()
