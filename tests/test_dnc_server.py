"""The DNC server against emulated controls through real links (pty and TCP): the remote
request end to end, received-program versions and diff, several machines at once, dnc.toml
refusals, one owner per link."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import urllib.error
import urllib.request
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from playwright.async_api import Browser

from cellctl.emulators.serve import Server, serve
from cellctl.errors import MachineInUse, UsageError
from cellctl.kinds.iso_cnc.dnc.cli import serve_shop
from cellctl.kinds.iso_cnc.dnc.config import load_shop, parse_dnc_file
from cellctl.kinds.iso_cnc.dnc.diff import compare
from cellctl.kinds.iso_cnc.dnc.server import Activity, DncServer
from cellctl.kinds.iso_cnc.dnc.store import ShopStore
from cellctl.kinds.iso_cnc.emulator import EmulatorOptions, IsoCncEmulator, Mode
from cellctl.link import LineSettings
from cellctl.service.client import attach
from cellctl.service.token import read_token
from tests.conftest import IN_BROWSER, SEEN_MS, free_port, until

LINE = LineSettings.parse("9600,7E2")
BRACKET = "O1234 (BRACKET)\nG21 G90 G17\nG00 X0 Y0 Z5.\nG01 Z-1. F300\nG01 X10. Y5.\nM30\n"
DRIP = "O5000 (SURFACE)\nG21 G90 G17\nG01 X1. F3000\nX2. Z-0.1\nX3. Z-0.2\nX4.\nX5.\nM30\n"


def write_shop(root: Path, links: dict[str, str], extra: str = "") -> Path:
    rows = [
        f'[machines.{name}]\nlink = "{url}"\nline = "9600,7E2"\n' for name, url in links.items()
    ]
    root.mkdir(exist_ok=True)
    (root / "dnc.toml").write_text("\n".join(rows) + extra)
    return root


async def control(listen: str = "pty") -> tuple[IsoCncEmulator, Server]:
    emulator = IsoCncEmulator(EmulatorOptions())
    return emulator, await serve(emulator, listen, LINE)


@pytest.fixture
async def one(tmp_path: Path) -> AsyncIterator[tuple[IsoCncEmulator, DncServer, ShopStore]]:
    emulator, server = await control()
    shop = write_shop(tmp_path / "shop", {"mill1": server.url})
    store = ShopStore(shop)
    (store.machine("mill1") / "programs" / "O1234.nc").write_text(BRACKET)
    (store.machine("mill1") / "programs" / "O5000.nc").write_text(DRIP)
    dnc = DncServer(load_shop(shop))
    await dnc.start()
    try:
        yield emulator, dnc, store
    finally:
        await dnc.close()
        await server.close()


async def punch(emulator: IsoCncEmulator, number: int, text: str) -> None:
    emulator.memory[number] = text
    emulator.set_mode(Mode.EDIT)
    emulator.punch(number)


async def test_remote_request_loads_the_program_on_the_next_read(
    one: tuple[IsoCncEmulator, DncServer, ShopStore],
) -> None:
    emulator, dnc, store = one
    await punch(emulator, 9999, "O9999 (LOAD O1234)\n")
    await until(lambda: dnc.status()["mill1"].activity is Activity.WAITING, "the request")
    assert dnc.status()["mill1"].pending == "load O1234"
    await until(lambda: emulator.activity == "idle", "the punch's end")
    emulator.read()  # the operator presses READ
    await until(lambda: 1234 in emulator.memory, "O1234 in the control's memory")
    assert emulator.memory[1234] == BRACKET
    await until(lambda: dnc.status()["mill1"].activity is Activity.IDLE, "the server idle")
    assert not emulator.alarms
    log = "\n".join(store.log_lines("mill1"))
    assert "request: load O1234" in log
    assert "O1234.nc: read in" in log
    assert [k.path.read_text() for k in store.sent("mill1", 1234)] == [BRACKET]
    assert store.received("mill1") == []  # a request is not a backup


async def test_remote_request_drip_feeds_when_marked(
    one: tuple[IsoCncEmulator, DncServer, ShopStore],
) -> None:
    emulator, dnc, _store = one
    await punch(emulator, 9999, "O9999 (DRIP O5000)\n")
    await until(lambda: dnc.status()["mill1"].pending == "drip-feed O5000", "the request")
    await until(lambda: emulator.activity == "idle", "the punch's end")
    emulator.set_mode(Mode.RMT)
    emulator.cycle_start()
    await until(lambda: emulator.runs and emulator.runs[-1].done, "the drip-feed's last block")
    assert emulator.runs[-1].blocks == 8
    assert not emulator.alarms
    await until(lambda: "drip-fed" in dnc.status()["mill1"].last, "the server's record")


async def test_a_request_for_a_missing_program_is_refused_and_logged(
    one: tuple[IsoCncEmulator, DncServer, ShopStore],
) -> None:
    emulator, dnc, store = one
    await punch(emulator, 9999, "O9999 (LOAD O4321)\n")
    await until(lambda: "refused" in dnc.status()["mill1"].last, "the refusal")
    assert "no program O4321" in dnc.status()["mill1"].error
    assert dnc.status()["mill1"].pending == ""
    # the refused request's punch is kept as received, as docs/dnc.md says
    (kept,) = store.received("mill1", 9999)
    assert kept.path.read_text() == "O9999 (LOAD O4321)\n"
    await punch_after_idle(emulator, 9999, "O9999 (HELLO)\n")
    await until(lambda: len(store.received("mill1", 9999)) == 2, "the odd request kept")
    assert "asks for nothing" in "\n".join(store.log_lines("mill1"))


async def test_a_request_for_a_program_the_read_would_refuse_is_refused_and_kept(
    one: tuple[IsoCncEmulator, DncServer, ShopStore],
) -> None:
    """An empty program, or one with a block longer than the control takes: refused when
    requested (the log says why, the request kept as received), not a failed read-in later."""
    emulator, dnc, store = one
    programs = store.machine("mill1") / "programs"
    (programs / "O1006.nc").write_text("")
    (programs / "O1004.nc").write_text("O1004\nG01 X1. " + "(" + "A" * 5000 + ")\nM30\n")
    for number, words in ((1006, "O1006:1: no blocks"), (1004, "O1004:2:")):
        await punch_after_idle(emulator, 9999, f"O9999 (LOAD O{number})\n")
        await until(lambda n=number: f"O{n}" in dnc.status()["mill1"].last, "the refusal")
        status = dnc.status()["mill1"]
        assert "refused" in status.last and words in status.error, status
        assert status.pending == "" and status.activity is Activity.IDLE
    assert len(store.received("mill1", 9999)) == 2
    log = "\n".join(store.log_lines("mill1"))
    assert "read in FAILED" not in log and log.count("refused:") == 2, log


async def punch_after_idle(emulator: IsoCncEmulator, number: int, text: str) -> None:
    await until(lambda: emulator.activity == "idle", "the control idle")
    await punch(emulator, number, text)


async def test_received_programs_are_versions_and_diff_against_what_was_sent(
    one: tuple[IsoCncEmulator, DncServer, ShopStore],
) -> None:
    emulator, dnc, store = one
    await punch(emulator, 9999, "O9999 (LOAD O1234)\n")
    await until(lambda: dnc.status()["mill1"].activity is Activity.WAITING, "the request")
    await until(lambda: emulator.activity == "idle", "the punch's end")
    emulator.read()
    await until(lambda: store.sent("mill1", 1234), "O1234 sent")
    # edited at the machine, punched back twice
    edited = BRACKET.replace("X10. Y5.", "X12. Y5.")
    await punch_after_idle(emulator, 1234, edited)
    await until(lambda: len(store.received("mill1", 1234)) == 1, "the first copy")
    await punch_after_idle(emulator, 1234, BRACKET)
    await until(lambda: len(store.received("mill1", 1234)) == 2, "the second copy")
    first, second = store.received("mill1", 1234)
    assert first.path != second.path
    sent = store.sent("mill1", 1234)[-1].path.read_bytes()
    result = compare(sent, first.path.read_bytes())
    assert not result.same
    assert "+G01 X12. Y5." in result.text
    assert compare(sent, second.path.read_bytes()).same


async def test_several_machines_from_one_server(tmp_path: Path) -> None:
    served = [await control("pty"), await control("socket://127.0.0.1:0"), await control("pty")]
    links = {f"mill{i}": s.url for i, (_, s) in enumerate(served)}
    shop = write_shop(tmp_path / "shop", links)
    dnc = DncServer(load_shop(shop))
    await dnc.start()
    try:
        for i, (emulator, _) in enumerate(served):
            await punch(emulator, 100 + i, f"O{100 + i:04d} (PART {i})\nG00 X{i}.\nM30\n")
        store = ShopStore(shop)
        for i in range(3):
            await until(lambda i=i: store.received(f"mill{i}", 100 + i), f"mill{i}'s program")
            (kept,) = store.received(f"mill{i}")
            assert kept.number == 100 + i
            assert f"(PART {i})" in kept.path.read_text()
        assert {s.activity for s in dnc.status().values()} == {Activity.IDLE}
    finally:
        await dnc.close()
        for _, server in served:
            await server.close()


async def test_the_api_sends_no_file_from_outside_the_shop(tmp_path: Path) -> None:
    """``dnc.send`` names a program of the shop (or carries its text): a path of the
    server's host outside the shop's program folders (outside the shop, straight or through
    ``..``, or one of its own files: its token, its dnc.toml) is refused before a byte goes
    out, and the file is not read; a file of a machine's programs/ is sent."""
    emulator, server = await control()
    shop = write_shop(tmp_path / "shop", {"mill1": server.url})
    programs = ShopStore(shop).machine("mill1") / "programs"
    (programs / "O1234.nc").write_text(BRACKET)
    secret = tmp_path / "O7777.nc"  # beside the shop, not in it
    secret.write_text("O7777 (NOT FOR THE SHOP)\nG00 X0\nM30\n")
    stop = asyncio.Event()
    task = asyncio.create_task(serve_shop(load_shop(shop), stop=stop))
    client = None
    try:
        await until(lambda: task.done() or (shop / "api.sock").exists(), "the API listening")
        assert not task.done(), task.exception()
        client = await attach(shop)
        secrets = (shop / "api-token", shop / "dnc.toml")  # in the shop, and no program
        for named in (
            str(secret),
            str(programs / ".." / ".." / ".." / "O7777.nc"),
            *map(str, secrets),
            str(programs / ".." / ".." / "api-token"),
        ):
            with pytest.raises(UsageError, match="not in the shop's programs"):
                await client.call("dnc.send", {"machine": "mill1", "program": named})
        assert not emulator.memory  # nothing reached the control
        log = await client.call("dnc.log", {"machine": "mill1"})
        assert "NOT FOR THE SHOP" not in json.dumps(log)
        # Under the shop, by its path: sent (the operator presses READ).
        emulator.set_mode(Mode.EDIT)
        send = asyncio.create_task(
            client.call("dnc.send", {"machine": "mill1", "program": str(programs / "O1234.nc")})
        )

        async def offered() -> bool:
            status = await client.call("cell.status")
            return send.done() or status["machines"]["mill1"]["progress"] is not None

        await until(offered, "the read-in offered, waiting for READ")
        emulator.read()
        assert (await send)["machine"] == "mill1"
        assert "(BRACKET)" in emulator.memory[1234]
    finally:
        if client is not None:
            await client.close()
        stop.set()
        await task
        await server.close()


async def test_a_second_opener_of_a_served_link_is_refused(tmp_path: Path) -> None:
    _emulator, server = await control()
    shop = write_shop(tmp_path / "shop", {"mill1": server.url})
    dnc = DncServer(load_shop(shop))
    await dnc.start()
    try:
        other = write_shop(tmp_path / "other", {"again": server.url})
        second = DncServer(load_shop(other))
        with pytest.raises(MachineInUse, match="is in use by"):
            await second.start()
        assert dnc.status()["mill1"].activity is Activity.IDLE
    finally:
        await dnc.close()
        await server.close()
    await asyncio.sleep(0)


@pytest.mark.parametrize(
    ("toml", "said"),
    [
        ("[machines.m]\n", "link: Field required"),
        ('[machines.m]\nlink = "loop://"\nspeed = 1\n', "speed: unknown key"),
        ('[machines.m]\nlink = "loop://"\nline = "fast"\n', "line = 'fast'"),
        ('[machines.m]\nlink = "loop://"\noptions = { dc3_tolerance = -1 }\n', "dc3_tolerance"),
        ('[machines.m]\nlink = "loop://"\noptions = { colour = 1 }\n', "colour: unknown option"),
        ('[machines.m]\nlink = "loop://"\nkind = "dyna2400"\n', "feeds iso-cnc controls"),
        ('[machines."a b"]\nlink = "loop://"\n', "cannot be a directory name"),
        ('[machines.a]\nlink = "/dev/x"\n[machines.b]\nlink = "/dev/x"\n', "both on /dev/x"),
        (
            '[machines.a]\nlink = "socket://127.0.0.1:17110"\n'
            '[machines.b]\nlink = "socket://localhost:17110"\n',
            "both on socket://localhost:17110 (socket://127.0.0.1:17110 is the same link)",
        ),
        ('[machines.m]\nlink = "loop://"\nrequest = { program = 0 }\n', "request.program"),
        ("[dnc]\n", "no [machines.NAME] table"),
        ("[machines.m\n", "not valid TOML"),
        (
            '[dnc]\nlisten = "0.0.0.0:7130"\n[machines.m]\nlink = "loop://"\n',
            "only with allow_remote = true in [dnc]",
        ),
    ],
)
def test_dnc_toml_refusals(tmp_path: Path, toml: str, said: str) -> None:
    (tmp_path / "dnc.toml").write_text(toml)
    with pytest.raises(UsageError, match=r"dnc\.toml") as caught:
        load_shop(tmp_path)
    assert said in str(caught.value)


@contextlib.asynccontextmanager
async def listening_shop(
    tmp_path: Path,
) -> AsyncIterator[tuple[IsoCncEmulator, Path, int, asyncio.Task[None]]]:
    """A shop of one emulated control, mill1, served with ``[dnc] listen`` on a free loopback
    port: the control, the shop's directory, the port and the serving task (stopped after)."""
    emulator, server = await control("socket://127.0.0.1:0")
    port = free_port()
    shop = write_shop(
        tmp_path / "shop", {"mill1": server.url}, f'\n[dnc]\nlisten = "127.0.0.1:{port}"\n'
    )
    stop = asyncio.Event()
    task = asyncio.create_task(serve_shop(load_shop(shop), stop=stop))
    try:
        yield emulator, shop, port, task
    finally:
        stop.set()
        await task
        await server.close()


async def test_status_and_dashboard_through_the_api_on_dnc_listen(tmp_path: Path) -> None:
    async with listening_shop(tmp_path) as (emulator, shop, port, task):
        await until(lambda: (shop / "api-token").exists(), "the API's token")
        token = (shop / "api-token").read_text().strip()

        def get(path: str, bearer: str) -> tuple[int, bytes]:
            request = urllib.request.Request(
                f"http://127.0.0.1:{port}{path}", headers={"Authorization": f"Bearer {bearer}"}
            )
            try:
                with urllib.request.urlopen(request, timeout=10) as answer:
                    return answer.status, answer.read()
            except urllib.error.HTTPError as e:
                return e.code, b""

        async def status() -> dict[str, object]:
            code, body = await asyncio.to_thread(get, "/api/status", token)
            assert code == 200
            machine: dict[str, object] = json.loads(body)["machines"]["mill1"]
            return machine

        await until(lambda: task.done() or (shop / "api.sock").exists(), "the API listening")
        machine = await status()
        assert machine["kind"] == "iso-cnc" and machine["condition"] == "idle"
        assert (await asyncio.to_thread(get, "/api/status", "x" * 43))[0] == 401
        code, page = await asyncio.to_thread(get, "/", token)
        assert code == 200 and b"<html" in page.lower()
        await punch(emulator, 9999, "O9999 (DRIP O5000)\n")  # no O5000: refused, shown
        seen: list[dict[str, object]] = [{}]

        async def refused() -> bool:
            seen[0] = await status()
            return "no program O5000" in str(seen[0].get("error"))

        try:
            await until(refused, "the request for O5000 refused, shown as mill1's error", 30)
        except AssertionError as e:
            raise AssertionError(f"{e}; mill1: {seen[0]}") from None


def surfacing(moves: int) -> str:
    """A drip-feed program of 0.1 mm moves: the machine eats them faster than 9600 baud
    brings them, so its axes stop and wait for data (it stalls)."""
    rows = [f"X{i / 10:.1f} Y{i % 2 / 10:.1f}\n" for i in range(1, moves + 1)]
    return "O5000 (SURFACE)\nG21 G90 G17\nG01 X0 Y0 F3000\n" + "".join(rows) + "M30\n"


@IN_BROWSER
async def test_the_dashboard_shows_a_drip_feeds_stall_in_its_own_field(
    tmp_path: Path,
    browser: Browser,
) -> None:
    """A drip-feed that outruns the line, in Chromium: the machine's card shows its stall
    (the status' progress.stall_s) in a field of its own, growing above 0 while it runs,
    and hides it once the machine is idle again."""
    async with listening_shop(tmp_path) as (emulator, shop, port, task):
        (ShopStore(shop).machine("mill1") / "programs" / "O5000.nc").write_text(surfacing(300))
        await _stall_shown(emulator, shop, port, task, browser)


async def _stall_shown(
    emulator: IsoCncEmulator, shop: Path, port: int, task: asyncio.Task[None], browser: Browser
) -> None:
    context = await browser.new_context(viewport={"width": 1200, "height": 900})
    client = None
    try:
        await until(lambda: task.done() or (shop / "api.sock").exists(), "the API listening")
        assert not task.done(), task.exception()
        page = await context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        await page.goto(f"http://127.0.0.1:{port}/#token={read_token(shop)}")
        card = page.locator('.card[data-machine="mill1"]')
        await card.locator(".machine-state").wait_for(timeout=SEEN_MS)
        stall = card.locator(".stall")
        assert not await stall.is_visible()  # idle: no drip-feed, no stall field

        client = await attach(shop)
        emulator.set_mode(Mode.RMT)
        drip = {"machine": "mill1", "program": "O5000", "drip": True}
        send = asyncio.create_task(client.call("dnc.send", drip, timeout=120))

        async def offered() -> bool:
            status = await client.call("cell.status")
            return send.done() or status["machines"]["mill1"]["progress"] is not None

        await until(offered, "the drip-feed offered, waiting for CYCLE START")
        emulator.cycle_start()
        # Under way: the field shows a stall above 0 s, from the status' own figure.
        await page.wait_for_function(
            """() => {
              const s = document.querySelector('.card[data-machine="mill1"] .stall-s');
              return s && s.offsetParent !== null && parseFloat(s.textContent) > 0;
            }""",
            timeout=30_000,
        )
        assert (await card.locator(".stall-label").inner_text()).strip() == "stalled"
        async with asyncio.timeout(60):
            result = await send
        assert "drip-fed" in result["message"] and "stalled" in result["message"]
        assert emulator.runs[-1].stall_s > 0
        # Idle again: the field goes with the progress.
        await stall.wait_for(state="hidden", timeout=SEEN_MS)
        assert not errors, errors
    finally:
        if client is not None:
            await client.close()
        await context.close()


@IN_BROWSER
async def test_the_dashboard_shows_a_punchs_characters_with_no_total(
    tmp_path: Path,
    browser: Browser,
) -> None:
    """A punch under way, in Chromium: its card counts the characters come so far, never a
    share of a total no one knows before the DC4 (it showed "N / 0 chars")."""
    async with listening_shop(tmp_path) as (emulator, shop, port, task):
        context = await browser.new_context(viewport={"width": 1200, "height": 900})
        try:
            await until(lambda: task.done() or (shop / "api.sock").exists(), "the API listening")
            assert not task.done(), task.exception()
            page = await context.new_page()
            await page.goto(f"http://127.0.0.1:{port}/#token={read_token(shop)}")
            card = page.locator('.card[data-machine="mill1"]')
            await card.locator(".machine-state").wait_for(timeout=SEEN_MS)
            emulator.memory[5000] = surfacing(4000)  # some 50 s of line: still coming when seen
            emulator.punch(5000)
            await page.wait_for_function(
                """() => {
                  const t = document.querySelector('.card[data-machine="mill1"] .progress-text');
                  return t && /[1-9][0-9]* chars/.test(t.textContent);
                }""",
                timeout=30_000,
            )
            text = await card.locator(".progress-text").inner_text()
            assert not re.search(r"/ ?\d+ chars", text) and "%" not in text, text
        finally:
            await context.close()


def test_machines_from_a_cell(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    cell.mkdir()
    (cell / "cell.toml").write_text(
        '[machines.cnc1]\nkind = "dyna2400"\nlink = "loop://a"\n\n'
        '[machines.haas]\nkind = "iso-cnc"\nlink = "loop://b"\nline = "19200,7E1"\n'
        "options = { dc3_tolerance = 2 }\n"
    )
    shop = load_shop(tmp_path / "shop", cell=cell)
    assert list(shop.machines) == ["haas"]
    assert shop.machines["haas"].options.dc3_tolerance == 2
    assert shop.machines["haas"].settings.baudrate == 19200
    (cell / "cell.toml").write_text('[machines.cnc1]\nkind = "dyna2400"\nlink = "loop://a"\n')
    with pytest.raises(UsageError, match="no machine of kind iso-cnc"):
        load_shop(tmp_path / "shop", cell=cell)


_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=10), inner, max_size=3)
    ),
    max_leaves=12,
)


@settings(max_examples=200, deadline=None)
@given(
    st.dictionaries(
        st.sampled_from(["dnc", "machines", "other"]),
        st.dictionaries(
            st.text(max_size=12),
            st.dictionaries(
                st.sampled_from(["link", "line", "options", "request", "kind", "x"]), _VALUES
            )
            | _VALUES,
            max_size=3,
        ),
        max_size=3,
    )
)
def test_any_dnc_toml_is_a_shop_or_a_refusal(data: dict[str, object]) -> None:
    path = Path("/nonexistent/dnc.toml")
    try:
        shop = parse_dnc_file(data, path.parent, path)
    except UsageError as e:
        assert str(path) in str(e)
    else:
        assert shop.machines


def test_a_shop_without_dnc_toml_is_told_both_ways_to_give_one(tmp_path: Path) -> None:
    with pytest.raises(UsageError) as refused:
        load_shop(tmp_path)
    said = str(refused.value)
    assert f"no {tmp_path / 'dnc.toml'}: write one (docs/dnc.md)" in said
    assert "--cell DIR --use-cell" in said  # the option that does it, as spelled
