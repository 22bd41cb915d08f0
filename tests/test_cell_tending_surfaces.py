"""The cobot-tending cell on the surfaces, with nothing kind-specific in their code: the
dashboard's floor (drawn from the layout) and machine cards in a real Chromium, and OPC UA's
machines with their makers, for a cell of a UR, an iso-cnc control and a Dyna 2400."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import pytest_asyncio
from asyncua import ua
from asyncua.ua.uaerrors import UaError
from playwright.async_api import Browser

from cellctl.cell.config import load_cell
from cellctl.emulators.cell import EmulatedCell
from cellctl.factory.opcua import NAMESPACE
from cellctl.kinds import registry
from cellctl.service.client import attach
from cellctl.service.token import read_token
from cellctl.testing.rig import write_cell_options
from cellctl.ui.cell_cli import run_controller
from cellctl.ui.console.app import ConsoleApp
from tests.conftest import IN_BROWSER, SEEN_MS, free_port, until
from tests.test_console import wait_text
from tests.test_opcua import client_cert, session  # noqa: F401  (client_cert: the fixture)

# On the session's event loop, where the browser lives (tests/conftest.py).
pytestmark = IN_BROWSER

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell-tending"


@dataclass
class Running:
    directory: Path
    api: str  # http://HOST:PORT
    opcua: str  # opc.tcp://HOST:PORT


@pytest_asyncio.fixture(loop_scope="session")
async def running(tmp_path: Path) -> AsyncIterator[Running]:
    """The example emulated, its real controller running with the API on TCP and OPC UA."""
    emulated = EmulatedCell(time_scale=200.0, template=EXAMPLE)
    directory = tmp_path / "cell"
    await emulated.start(directory)
    api = f"127.0.0.1:{free_port()}"
    opcua = f"opc.tcp://127.0.0.1:{free_port()}"
    # OPC UA, the API and the emulated machines share this process with the controller: on a
    # loaded box the PLC's answer, or a look at an idle machine, can take over its deadline
    # (tests/conftest.py).
    write_cell_options(directory / "cell.toml", {"read_limit": 5.0}, {}, {"timeout": 5.0})
    with (directory / "cell.toml").open("a", encoding="utf-8") as toml:
        toml.write(
            f'\n[api]\nlisten = "{api}"\n\n[opcua]\nlisten = "{opcua}"\nanonymous_read = true\n'
        )
    stop = asyncio.Event()
    run = asyncio.create_task(run_controller(directory, live=False, until_idle=False, stop=stop))
    try:
        # api.sock appears once the API listens (on its socket and on [api] listen).
        await until(lambda: (directory / "api.sock").exists() or run.done(), "the API", 60)
        assert not run.done(), run.exception()
        yield Running(directory, f"http://{api}", opcua)
    finally:
        stop.set()
        async with asyncio.timeout(30):
            await run
        await emulated.close()


async def test_the_dashboard_draws_the_cobot_cell(
    running: Running,
    browser: Browser,
) -> None:
    config = load_cell(running.directory)
    context = await browser.new_context(viewport={"width": 1400, "height": 1000})
    try:
        page = await context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        await page.goto(f"{running.api}/#token={read_token(running.directory)}")
        plan = page.locator("#floor-plan svg")
        await plan.locator(f'.machine.robot[data-machine="{config.robot.name}"]').wait_for(
            timeout=SEEN_MS
        )
        mills = plan.locator(".machine.mill")
        await mills.first.wait_for(timeout=SEEN_MS)
        drawn = {await m.get_attribute("data-machine") for m in await mills.all()}
        assert drawn == {m.name for m in config.mills} == {"vf2", "cnc2"}
        # A card per machine, each with its state in words.
        for machine in [config.robot, *config.mills]:
            state = page.locator(f'.card[data-machine="{machine.name}"] .machine-state')
            await state.wait_for(timeout=SEEN_MS)
            assert (await state.inner_text()).strip(), machine.name
        assert not errors, errors
    finally:
        await context.close()


async def test_opc_ua_shows_the_cobot_cells_machines(
    running: Running,
    client_cert: tuple[str, str],  # noqa: F811
) -> None:
    config = load_cell(running.directory)
    cell = running.directory

    async def serving() -> bool:
        with contextlib.suppress(OSError, UaError, TimeoutError):
            async with session(running.opcua, cell, client_cert):
                return True
        return False

    await until(serving, "the OPC UA server", 60)
    async with session(running.opcua, cell, client_cert) as client:
        idx = await client.get_namespace_index(NAMESPACE)
        machines = await client.nodes.objects.get_child(f"{idx}:Machines")
        names = {(await n.read_browse_name()).Name for n in await machines.get_children()}
        assert names == {"robot", "vf2", "cnc2"}
        for machine in [config.robot, *config.mills]:
            maker = await client.get_node(
                ua.NodeId(f"Machines/{machine.name}/Identification/Manufacturer", idx)
            ).read_value()
            assert maker == registry.kind(machine.kind).maker, machine.name


async def test_the_console_attaches_to_the_cobot_cell(running: Running) -> None:
    """The console's board and main menu for a UR, an iso-cnc control and a Dyna 2400: the
    source's menu numbers, each machine on the board, the robot's menu from its kind."""
    client = await attach(running.directory)
    try:
        app = ConsoleApp(running.directory, client, traffic_period=0.1)
        async with app.run_test(size=(100, 30)) as pilot:
            shown = await wait_text(pilot, "attached to cellctl run (pid", "4. EXIT")
            for name in ("robot", "vf2", "cnc2"):
                assert name in shown, shown
            # 1. ROBOT: the functions the robot's kind declares, by their labels.
            menu = registry.kind(load_cell(running.directory).robot.kind).menu
            labels = [f.label for f in (menu() if menu is not None else ())]
            assert labels, "the robot's kind declares its functions"
            await pilot.press("1")
            await wait_text(pilot, *labels[:4])
    finally:
        await client.close()
