"""The console with an operator's token: a machine function only an engineer may run is
refused at once, in the server's words, before its dialog and before the machine is taken
out of automatic service for it; what an operator may do (take a machine out, read its
status) still works. ``server.info`` names the caller's role and each method's.

The cell is the emulated one on real ptys and sockets, its controller and API in this
process; the console is driven with Textual's Pilot at 80x24, with a token of each role.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

import pytest

from cellctl.service.access import AttachedCell
from cellctl.service.client import RemoteCell
from cellctl.service.server import ApiServer
from cellctl.testing.rig import CellRig
from cellctl.ui.console.app import ConsoleApp
from tests.test_console import SIZE, wait_text

Connect = Callable[[str], Any]


@pytest.fixture
async def served(tmp_path: Any) -> AsyncIterator[tuple[CellRig, Connect]]:
    """A running cell (controller and API in this process), and a way to connect to it with
    a new token of a given role."""
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        assert rig.controller is not None
        server = ApiServer(AttachedCell(rig.controller), rig.directory)
        await server.start()

        @asynccontextmanager
        async def connect(role: str) -> AsyncIterator[RemoteCell]:
            result = await rig.cli("token", "add", f"{role[:3]}1", "--role", role)
            assert result.exit_code == 0, result.output
            token = result.output.splitlines()[0].strip()
            client = await RemoteCell.connect(token=token, socket_path=server.socket_path)
            try:
                yield client
            finally:
                await client.close()

        try:
            yield rig, connect
        finally:
            await server.close()


async def test_server_info_names_the_callers_role_and_each_methods(
    served: tuple[CellRig, Connect],
) -> None:
    _, connect = served
    async with connect("operator") as client:
        info = await client.call("server.info")
    assert info["caller"] == {"who": "token:ope1", "role": "operator"}
    assert info["roles"]["mill.end"] == "engineer"
    assert info["roles"]["machines.out_of_service"] == "operator"
    assert info["roles"]["server.info"] == "viewer"
    assert set(info["roles"]) == set(info["methods"])


async def test_an_operator_is_refused_an_engineers_function_before_anything_is_done(
    served: tuple[CellRig, Connect],
) -> None:
    rig, connect = served
    async with connect("operator") as client:
        app = ConsoleApp(rig.directory, client, traffic_period=0.1)
        async with app.run_test(size=SIZE) as pilot:
            await wait_text(pilot, "attached to cellctl run")
            await pilot.press("3")
            await wait_text(pilot, "NC MACHINE #2 (cnc2)", "s. OUT OF SERVICE")
            await pilot.press("5")  # HALT: the engineer's
            await wait_text(
                pilot, "cnc2: HALT: ope1 is an operator: mill.end needs the engineer role"
            )
            # Not asked to take cnc2 out, and not taken out: the cell goes on with it.
            await pilot.press("1")  # INITIALIZE (a dialog first, for an engineer)
            shown = await wait_text(
                pilot, "cnc2: INITIALIZE: ope1 is an operator: mill.init needs the engineer"
            )
            assert "automatic service. Take it out" not in shown
            assert "Force (initialize again)" not in shown  # no dialog for nothing
            assert rig.journal.machines_out_of_service() == {}
            # What an operator may do still works: the status (a viewer's read).
            await pilot.press("4")
            await wait_text(pilot, "cnc2: STATUS: state")
            await pilot.press("q")
        assert app.return_code == 0
    assert not rig.cut_twice(), rig.describe()
