"""Refused logins through the real API server (HTTP, the dashboard's call, the WebSocket on
api.sock): each is in the audit trail (``cellctl audit --since 1m``) and the run log, through
``ApiServer.login_refused`` where the server and the dashboard refuse a token or an origin."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cellctl.errors import AccessDenied
from cellctl.service.client import RemoteCell
from cellctl.service.logins import LOGIN, WRONG_TOKEN
from cellctl.service.token import add_token, revoke_token
from cellctl.testing.rig import CellRig
from cellctl.testing.rig import cli as rig_cli
from tests.test_dashboard import dashboard_served, http


async def test_wrong_revoked_and_cross_site_logins_are_audited_and_logged(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        assert rig.controller is not None
        async with dashboard_served(rig) as (server, base):
            cell = rig.directory
            ann = add_token(cell, "ann", "operator")
            revoke_token(cell, "ann")
            for _ in range(3):
                status, _ = await http(base + "/api/status", token="wrong-" + "x" * 40)
                assert status == 401
            status, _ = await http(base + "/api/orders", token=ann)
            assert status == 401
            call = {"method": "cell.pause", "params": {}}
            status, _ = await http(
                base + "/dashboard/call",
                token=server.token,
                body=call,
                headers={"Origin": "http://evil.example"},
            )
            assert status == 403
            with pytest.raises(AccessDenied):
                await RemoteCell.connect(token="wrong-" + "y" * 40, socket_path=server.socket_path)
            result = await rig_cli(cell, "audit", "--since", "1m", "--json")
            assert result.exit_code == 0, result.output
            found = [
                (e["who"], json.loads(e["params"])["asked"], e["repeats"])
                for e in json.loads(result.output)
                if e["method"] == LOGIN
            ]
            assert found == [
                ("unknown token", "GET /api/status", 4),  # the socket's WebSocket counted too
                ("token:ann (revoked)", "GET /api/orders", 1),
                ("token:default", "POST /dashboard/call", 1),
            ], found
            events = " | ".join(e.text for e in rig.controller.events)
            assert events.count("login refused for unknown token") == 1, events
            assert "login refused for token:ann (revoked) from 127.0.0.1:" in events
            assert WRONG_TOKEN in events and server.token not in events and ann not in events
